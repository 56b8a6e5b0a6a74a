/*
 * rlb_twist HOST PORT TOPIC COUNT [--psk-file FILE]
 *
 * Whole messages: publishes COUNT geometry_msgs/msg/Twist maps (linear.x = i, angular.z = -i)
 * built with rlb_msg_*, and reads them back through the server on a whole-message channel
 * and on a field-bound one (angular.z) of the same session, printing per message
 * "linear.x angular.z field", read with rlb_msg_get_*. Then it writes one map with a field
 * Twist does not have and prints the error the server answered for that channel
 * ("error 13" = BAD_VALUE). Exit 0 when all of it happened, 1 otherwise.
 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "common.h"

static int build_twist(uint8_t *buf, size_t cap, double x, double z) {
    rlb_msg m;
    rlb_msg_init(&m, buf, cap);
    rlb_msg_map(&m, 2);
    rlb_msg_key(&m, "linear");
    rlb_msg_map(&m, 1);
    rlb_msg_key(&m, "x");
    rlb_msg_f64(&m, x);
    rlb_msg_key(&m, "angular");
    rlb_msg_map(&m, 1);
    rlb_msg_key(&m, "z");
    rlb_msg_f64(&m, z);
    return rlb_msg_end(&m);
}

static void sleep_ms(long ms) {
    struct timespec ts = {ms / 1000, (ms % 1000) * 1000000};
    nanosleep(&ts, NULL);
}

int main(int argc, char **argv) {
    args a;
    parse_args(argc, argv, "HOST PORT TOPIC COUNT [--psk-file FILE]", &a);
    rlb_config cfg;
    uint8_t key[RLB_MAX_KEY];
    config_from(&a, "rlb_twist", "rlb_twist", &cfg, key);
    rlb_client *c;
    if (rlb_client_new(&cfg, &c) != RLB_OK) return 1;
    rlb_channel_opts o;
    rlb_channel *pub, *whole, *field;
    rlb_channel_opts_init(&o, a.topic, "geometry_msgs/msg/Twist", NULL);
    o.value_bytes = 256; /* a whole Twist as the server sends it: six float64 and the keys */
    o.capacity = a.count < 64 ? 64 : (uint32_t)a.count;
    o.mode = RLB_QUEUE;
    o.transport = RLB_TCP;
    int rc = rlb_publish(c, &o, &pub);
    if (rc == RLB_OK) rc = rlb_subscribe(c, &o, &whole);
    o.field = "angular.z";
    o.value_bytes = 16;
    if (rc == RLB_OK) rc = rlb_subscribe(c, &o, &field);
    if (rc == RLB_OK) rc = rlb_connect(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rlb_twist: cannot connect to %s:%u: %s\n", a.host, (unsigned)a.port,
                rlb_status_text(rc));
        rlb_close(c);
        return 1;
    }
    rlb_start(c);
    uint8_t buf[256];
    for (unsigned long i = 0; i < a.count; i++) {
        int len = build_twist(buf, sizeof buf, (double)i, -(double)i);
        if (len < 0 || rlb_write_raw(pub, buf, (size_t)len) != RLB_OK) return 1;
        sleep_ms(5);
    }
    unsigned long got = 0;
    while (got < a.count && rlb_read_wait(whole, 10000) == RLB_NEW) {
        size_t len;
        double x, z, fz;
        while (got < a.count && rlb_read_raw(whole, buf, sizeof buf, &len) == RLB_NEW) {
            if (rlb_msg_get_f64(buf, len, "linear.x", &x) != RLB_OK ||
                rlb_msg_get_f64(buf, len, "angular.z", &z) != RLB_OK ||
                rlb_read_wait(field, 10000) != RLB_NEW || rlb_read_f64(field, &fz) != RLB_NEW) {
                fprintf(stderr, "rlb_twist: message %lu not readable\n", got);
                rlb_close(c);
                return 1;
            }
            printf("%g %g %g\n", x, z, fz);
            got++;
        }
    }
    fflush(stdout);
    /* a field Twist does not have: the server refuses the value, the channel shows it */
    rlb_msg m;
    rlb_msg_init(&m, buf, sizeof buf);
    rlb_msg_map(&m, 1);
    rlb_msg_key(&m, "sideways");
    rlb_msg_f64(&m, 1.0);
    rlb_write_raw(pub, buf, (size_t)rlb_msg_end(&m));
    rlb_channel_stats st = {0};
    for (int i = 0; i < 1000 && st.last_error == 0; i++) {
        sleep_ms(10);
        rlb_channel_stats_get(pub, &st);
    }
    printf("error %d\n", st.last_error);
    rlb_close(c);
    return got == a.count && st.last_error != 0 ? 0 : 1;
}
