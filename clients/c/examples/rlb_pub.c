/*
 * rlb_pub HOST PORT TOPIC COUNT RATE_HZ [--tcp] [--psk-file FILE] [--channels N] [--udp-only]
 *
 * A periodic loop (SCHED_FIFO when permitted, memory locked) publishes std_msgs/msg/Float64
 * field data values 0, 1, ..., COUNT-1 at RATE_HZ, then waits until the I/O side has sent
 * them all and exits 0; 1 with one line on stderr when it cannot connect. --channels N: the
 * same values on N channels, topics TOPIC_0 .. TOPIC_{N-1} (over UDP, one datagram per round
 * carries them all). --udp-only: a UDP-only session (protocol.md 8.2), for a server without
 * TCP. --tls-ca FILE / --tls-fingerprint HEX: TLS, the server verified by that CA or pinned;
 * --tls-cert/--tls-key: a client certificate (a server with --tls-client-ca). --redundancy K:
 * each datagram repeats the previous K values (protocol.md 10.3). --mixed (with --channels N):
 * TOPIC_1, TOPIC_3, ... over TCP, the others over UDP.
 * The loop thread makes no system call but its sleep (clock_nanosleep) and clock reads.
 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "common.h"

#define MAX_CHANNELS 256

typedef struct loop {
    rlb_channel *ch[MAX_CHANNELS];
    unsigned n;
    unsigned long count;
    long period_ns;
    unsigned long full; /* periods in which a ring was full: the value waits a period */
    unsigned long done[MAX_CHANNELS]; /* values written per channel */
} loop;

static void *run(void *arg) {
    loop *l = arg;
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (unsigned long i = 0; i < l->count;) {
        next.tv_nsec += l->period_ns;
        while (next.tv_nsec >= 1000000000) {
            next.tv_nsec -= 1000000000;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        bool all = true; /* a channel whose ring was full gets the value again next period */
        for (unsigned k = 0; k < l->n; k++)
            if (l->done[k] <= i) {
                if (rlb_write_f64(l->ch[k], (double)i) == RLB_OK) l->done[k] = i + 1;
                else all = false;
            }
        if (all) i++;
        else l->full++;
    }
    return NULL;
}

/* Keeps the server's last reason (a refused binding or session) for the one error line;
 * says at once which values rlb_close could not get confirmed (counted as lost). */
static void on_event(void *ctx, const rlb_event *ev) {
    if (ev->kind == RLB_EV_UNCONFIRMED) fprintf(stderr, "rlb_pub: %s\n", ev->reason);
    if (ev->kind == RLB_EV_TOPIC_ERROR || ev->kind == RLB_EV_DISCONNECT || ev->kind == RLB_EV_ERROR)
        snprintf(ctx, 256, " (server: code %d, %s)", ev->code, ev->reason);
}

int main(int argc, char **argv) {
    args a;
    parse_args(argc, argv,
               "HOST PORT TOPIC COUNT RATE_HZ [--tcp] [--psk-file FILE] [--channels N] [--udp-only] "
               "[--redundancy K] [--mixed] "
               "[--tls-ca FILE | --tls-fingerprint HEX] [--tls-cert FILE --tls-key FILE]",
               &a);
    rlb_config cfg;
    uint8_t key[RLB_MAX_KEY];
    config_from(&a, "rlb_pub", "rlb_pub", &cfg, key);
    char reason[256] = "";
    cfg.on_event = on_event;
    cfg.event_ctx = reason;
    cfg.max_channels = a.channels;
    rlb_client *c;
    rlb_status rc = rlb_client_new(&cfg, &c);
    if (rc != RLB_OK) {
        setup_failed("rlb_pub", &a, rc);
        return 1;
    }
    static loop l; /* static: the per-channel arrays stay off the stack */
    l.n = a.channels;
    l.count = a.count;
    l.period_ns = (long)(1e9 / a.number);
    for (unsigned k = 0; k < a.channels; k++) {
        char topic[300];
        if (a.channels == 1) snprintf(topic, sizeof topic, "%s", a.topic);
        else snprintf(topic, sizeof topic, "%s_%u", a.topic, k);
        rlb_channel_opts o;
        rlb_channel_opts_init(&o, topic, "std_msgs/msg/Float64", "data");
        o.transport = a.tcp || (a.mixed && k % 2 == 1) ? RLB_TCP : RLB_UDP;
        o.capacity = 4096;
        o.redundancy = o.transport == RLB_UDP ? (uint8_t)a.redundancy : 0;
        if ((rc = rlb_publish(c, &o, &l.ch[k])) != RLB_OK) {
            fprintf(stderr, "rlb_pub: bad channel %s: %s\n", topic, rlb_status_text(rc));
            rlb_close(c);
            return 1;
        }
    }
    if ((rc = rlb_connect(c)) != RLB_OK) {
        fprintf(stderr, "rlb_pub: cannot connect to %s:%u: %s%s\n", a.host, (unsigned)a.port,
                rlb_status_text(rc), reason);
        rlb_close(c);
        return 1;
    }
    rlb_start(c);
    pthread_t t;
    bool fifo = start_rt_thread("rlb_pub", &t, run, &l);
    pthread_join(t, NULL);
    rc = rlb_flush(c, 30000);
    unsigned long long sent = 0;
    for (unsigned k = 0; k < l.n; k++) {
        rlb_channel_stats st;
        rlb_channel_stats_get(l.ch[k], &st);
        sent += st.values;
    }
    fprintf(stderr,
            "rlb_pub: %lu values written on %u channel(s) (%s), %llu sent, ring full %lu times\n",
            a.count, l.n, fifo ? "SCHED_FIFO" : "SCHED_OTHER", sent, l.full);
    rlb_close(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rlb_pub: not everything was sent: %s\n", rlb_status_text(rc));
        return 1;
    }
    return 0;
}
