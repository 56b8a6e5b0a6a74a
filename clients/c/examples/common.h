/* What the examples share: arguments, the key file, the set-up's error line (the real-time
 * loop thread is progs.h's, which the proof and benchmark programs use too). */
#ifndef RLB_EXAMPLES_COMMON_H
#define RLB_EXAMPLES_COMMON_H

#include <stdbool.h>
#include <stdint.h>

#include "progs.h"
#include "rlbridge.h"

typedef struct args {
    const char *host, *topic, *psk_file;
    const char *tls_ca, *tls_fingerprint; /* --tls-ca FILE / --tls-fingerprint HEX: TLS */
    const char *tls_cert, *tls_key;       /* --tls-cert FILE --tls-key FILE: mutual TLS */
    uint16_t port;
    unsigned long count;
    double number; /* RATE_HZ for rlb_pub, TIMEOUT_S for rlb_sub */
    bool tcp;
    bool spin; /* rlb_sub --spin: no I/O thread, rlb_spin_once from the reading thread */
    bool udp_only; /* --udp-only: a UDP-only session (for a server without TCP) */
    bool mixed;    /* rlb_pub --mixed: with --channels N, odd channels over TCP, even over UDP */
    unsigned channels;
    unsigned redundancy; /* --redundancy K: UDP datagrams repeat the previous K values */ /* rlb_pub --channels N: TOPIC_0 .. TOPIC_{N-1}, default 1: TOPIC */
} args;

/* Parses HOST PORT TOPIC COUNT [NUMBER] [--tcp] [--psk-file FILE] [--spin] [--channels N] [--udp-only] [--tls-ca FILE] [--tls-fingerprint HEX] (the options the
 * usage names; NUMBER when the usage has RATE_HZ or TIMEOUT_S); exits 2 with the usage. */
void parse_args(int argc, char **argv, const char *usage, args *a);
/* Fills cfg from a (and loads the key); exits 1 with one line if the key file is unusable. */
void config_from(const args *a, const char *prog, const char *name, rlb_config *cfg,
                 uint8_t key[RLB_MAX_KEY]);
/* The line for a client that could not be set up (rlb_client_new's status). */
void setup_failed(const char *prog, const args *a, int status);

#endif
