/* What rlb_pub and rlb_sub share: arguments, the key file and the real-time set-up. */
#ifndef RLB_EXAMPLES_COMMON_H
#define RLB_EXAMPLES_COMMON_H

#include <pthread.h>
#include <stdbool.h>
#include <stdint.h>

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
/* Starts fn as the loop thread: SCHED_FIFO (priority 80) when permitted, else normal.
 * Locks memory first (mlockall) when permitted. Returns whether it got SCHED_FIFO. */
bool start_rt_thread(pthread_t *t, void *(*fn)(void *), void *arg);

#endif
