/*
 * rlb_sub HOST PORT TOPIC COUNT TIMEOUT_S [--tcp] [--psk-file FILE] [--spin] [--udp-only]
 *
 * Prints every value of std_msgs/msg/Float64 field data on TOPIC, one per line, and exits 0
 * once COUNT values arrived, 1 on timeout. The channel keeps every value (RLB_QUEUE): over
 * UDP in a ring of COUNT values; over TCP in a ring of 64 with credit flow control, so the
 * server sends no more than the ring has room for. Link changes go to stderr ("link lost",
 * "connected"); the client reconnects by itself. --spin: no I/O thread, the reading thread
 * runs the I/O itself (rlb_spin_once, what a single-threaded target does). --udp-only: a
 * UDP-only session (protocol.md 8.2), for a server without TCP. --tls-ca FILE /
 * --tls-fingerprint HEX: TLS, the server verified by that CA or pinned. --redundancy K: the
 * server repeats the previous K values in each datagram; the duplicates are dropped, counted.
 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "common.h"

static void on_event(void *ctx, const rlb_event *ev) {
    int *lost = ctx;
    if (ev->kind == RLB_EV_LINK && ev->link == RLB_LINK_LOST && !*lost) {
        *lost = 1;
        fprintf(stderr, "rlb_sub: link lost\n");
    } else if (ev->kind == RLB_EV_CONNECTED) {
        *lost = 0;
        fprintf(stderr, "rlb_sub: connected\n");
    } else if (ev->kind == RLB_EV_ERROR || ev->kind == RLB_EV_TOPIC_ERROR) {
        fprintf(stderr, "rlb_sub: server error %d on channel %u: %s\n", ev->code, ev->channel,
                ev->reason);
    }
}

int main(int argc, char **argv) {
    args a;
    parse_args(argc, argv,
               "HOST PORT TOPIC COUNT TIMEOUT_S [--tcp] [--psk-file FILE] [--spin] [--udp-only] "
               "[--redundancy K] "
               "[--tls-ca FILE | --tls-fingerprint HEX]",
               &a);
    rlb_config cfg;
    uint8_t key[RLB_MAX_KEY];
    config_from(&a, "rlb_sub", "rlb_sub", &cfg, key);
    int lost = 0;
    cfg.on_event = on_event;
    cfg.event_ctx = &lost;
    rlb_client *c;
    rlb_status rc = rlb_client_new(&cfg, &c);
    if (rc != RLB_OK) {
        setup_failed("rlb_sub", &a, rc);
        return 1;
    }
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, a.topic, "std_msgs/msg/Float64", "data");
    o.transport = a.tcp ? RLB_TCP : RLB_UDP;
    o.mode = RLB_QUEUE;
    o.redundancy = (uint8_t)a.redundancy;
    o.capacity = a.tcp || a.count < 64 ? 64 : a.count > (1u << 20) ? (1u << 20) : (uint32_t)a.count;
    rlb_channel *ch;
    if ((rc = rlb_subscribe(c, &o, &ch)) != RLB_OK) {
        fprintf(stderr, "rlb_sub: bad channel %s: %s\n", a.topic, rlb_status_text(rc));
        rlb_close(c);
        return 1;
    }
    if ((rc = rlb_connect(c)) != RLB_OK) {
        fprintf(stderr, "rlb_sub: cannot connect to %s:%u: %s\n", a.host, (unsigned)a.port,
                rlb_status_text(rc));
        rlb_close(c);
        return 1;
    }
    fprintf(stderr, "rlb_sub: subscribed to %s over %s\n", a.topic, a.tcp ? "tcp" : "udp");
    if (!a.spin) rlb_start(c); /* else rlb_read_wait runs rlb_spin_once itself */
    struct timespec t0, now;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    unsigned long got = 0;
    int code = 0;
    while (got < a.count) {
        clock_gettime(CLOCK_MONOTONIC, &now);
        double left = a.number - (double)(now.tv_sec - t0.tv_sec) -
                      (double)(now.tv_nsec - t0.tv_nsec) / 1e9;
        if (left <= 0) {
            fprintf(stderr, "rlb_sub: timed out after %g s with %lu of %lu values\n", a.number,
                    got, a.count);
            code = 1;
            break;
        }
        if (rlb_read_wait(ch, (uint32_t)(left * 1000) + 1) != RLB_NEW) continue;
        double v;
        while (got < a.count && rlb_read_f64(ch, &v) == RLB_NEW) {
            printf("%.17g\n", v);
            got++;
        }
        fflush(stdout);
    }
    rlb_channel_stats st;
    rlb_channel_stats_get(ch, &st);
    fprintf(stderr,
            "rlb_sub: %lu values, %llu lost, %llu duplicates, %llu dropped, %llu sessions\n",
            got, (unsigned long long)st.lost, (unsigned long long)st.duplicates,
            (unsigned long long)st.dropped, (unsigned long long)rlb_sessions(c));
    rlb_close(c);
    return code;
}
