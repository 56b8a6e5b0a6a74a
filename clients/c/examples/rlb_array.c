/*
 * rlb_array HOST PORT TOPIC COUNT [--psk-file FILE]
 *
 * Arrays: publishes COUNT std_msgs/msg/Float64MultiArray field data values [i, i/2, -i]
 * (rlb_write_f64_array into fixed-size slots) and reads them back through the server on a
 * field-bound channel of the same session (rlb_read_f64_array), printing one array per line.
 * Needs a middleware that knows the type (rlbridge serve --adapter ros2). Exit 0 when every
 * array came back, 1 otherwise.
 */
#include <stdio.h>
#include <time.h>

#include "common.h"

#define N 3

int main(int argc, char **argv) {
    args a;
    parse_args(argc, argv, "HOST PORT TOPIC COUNT [--psk-file FILE]", &a);
    rlb_config cfg;
    uint8_t key[RLB_MAX_KEY];
    config_from(&a, "rlb_array", "rlb_array", &cfg, key);
    rlb_client *c;
    if (rlb_client_new(&cfg, &c) != RLB_OK) return 1;
    rlb_channel_opts o;
    rlb_channel *pub, *sub;
    rlb_channel_opts_init(&o, a.topic, "std_msgs/msg/Float64MultiArray", "data");
    o.value_bytes = rlb_array_bytes(N);
    o.capacity = a.count < 64 ? 64 : (uint32_t)a.count;
    o.mode = RLB_QUEUE;
    o.transport = RLB_TCP;
    int rc = rlb_subscribe(c, &o, &sub);
    if (rc == RLB_OK) rc = rlb_publish(c, &o, &pub);
    if (rc == RLB_OK) rc = rlb_connect(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rlb_array: cannot connect to %s:%u: %s\n", a.host, (unsigned)a.port,
                rlb_status_text(rc));
        rlb_close(c);
        return 1;
    }
    rlb_start(c);
    for (unsigned long i = 0; i < a.count; i++) {
        double v[N] = {(double)i, (double)i / 2, -(double)i};
        if (rlb_write_f64_array(pub, v, N) != RLB_OK) return 1;
        struct timespec ts = {0, 5000000};
        nanosleep(&ts, NULL);
    }
    unsigned long got = 0;
    while (got < a.count && rlb_read_wait(sub, 10000) == RLB_NEW) {
        double v[N];
        size_t n;
        while (got < a.count && rlb_read_f64_array(sub, v, N, &n) == RLB_NEW && n == N) {
            printf("%g %g %g\n", v[0], v[1], v[2]);
            got++;
        }
    }
    if (got < a.count) fprintf(stderr, "rlb_array: %lu of %lu arrays came back\n", got, a.count);
    rlb_close(c);
    return got == a.count ? 0 : 1;
}
