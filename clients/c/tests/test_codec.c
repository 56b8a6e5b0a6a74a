/* The decoder and the real-time side's rings without a server: protocol.md section 14's bytes,
 * hostile input, the ring and triple buffer semantics, the message accessors. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "internal.h"

static size_t unhex(const char *s, uint8_t *out) {
    size_t n = strlen(s) / 2;
    for (size_t i = 0; i < n; i++) {
        unsigned v;
        sscanf(s + 2 * i, "%2x", &v);
        out[i] = (uint8_t)v;
    }
    return n;
}

static void batch_of_section_14_5(void **state) {
    (void)state;
    uint8_t b[64];
    size_t n = unhex("9509020a92cf17979cfe362a0000cf17979cfe3639424092cb3fd0000000000000cbc000000000000000", b);
    mp_cur c;
    uint32_t len, ns, nv;
    uint64_t tag, ch, seq;
    int64_t st;
    double v;
    rlbi_mp_init(&c, b, n);
    assert_true(rlbi_mp_array(&c, &len) && len == 5);
    assert_true(rlbi_mp_u64(&c, &tag) && tag == 9);
    assert_true(rlbi_mp_u64(&c, &ch) && ch == 2);
    assert_true(rlbi_mp_u64(&c, &seq) && seq == 10);
    assert_true(rlbi_mp_array(&c, &ns) && ns == 2);
    assert_true(rlbi_mp_i64(&c, &st) && st == 1700000000000000000LL);
    assert_true(rlbi_mp_i64(&c, &st) && st == 1700000000001000000LL);
    assert_true(rlbi_mp_array(&c, &nv) && nv == 2);
    assert_true(rlbi_mp_f64(&c, &v) && v == 0.25);
    assert_true(rlbi_mp_f64(&c, &v) && v == -2.0);
    assert_true(c.p == c.end && !c.err);
}

static void truncated_and_hostile_input_is_an_error(void **state) {
    (void)state;
    uint8_t b[64];
    size_t n = unhex("9509020a92cf17979cfe362a0000cf17979cfe3639424092cb3fd0000000000000cbc000000000000000", b);
    for (size_t cut = 0; cut < n; cut++) { /* every prefix fails cleanly */
        mp_cur c;
        rlbi_mp_init(&c, b, cut);
        assert_false(rlbi_mp_skip(&c) && c.p == c.end && cut == n);
    }
    uint8_t huge[] = {0xdd, 0xff, 0xff, 0xff, 0xff, 0x01}; /* array32 claims 4 G elements */
    mp_cur c;
    rlbi_mp_init(&c, huge, sizeof huge);
    assert_false(rlbi_mp_skip(&c));
    uint8_t deep[4096];
    memset(deep, 0x91, sizeof deep); /* 4096 nested arrays, no leaf: no recursion, an error */
    rlbi_mp_init(&c, deep, sizeof deep);
    assert_false(rlbi_mp_skip(&c));
    deep[sizeof deep - 1] = 0x01;
    rlbi_mp_init(&c, deep, sizeof deep);
    assert_true(rlbi_mp_skip(&c) && c.p == c.end);
    uint8_t neg_uint[] = {0xd3, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff}; /* -1 as u64 */
    uint64_t u;
    rlbi_mp_init(&c, neg_uint, sizeof neg_uint);
    assert_false(rlbi_mp_u64(&c, &u));
    srand(7);
    for (int i = 0; i < 20000; i++) { /* random bytes never read past the end */
        uint8_t r[32];
        size_t len = (size_t)(rand() % 32);
        for (size_t j = 0; j < len; j++) r[j] = (uint8_t)rand();
        rlbi_mp_init(&c, r, len);
        if (rlbi_mp_skip(&c)) assert_true(c.p <= c.end);
    }
}

static void encoder_matches_section_14(void **state) {
    (void)state;
    uint8_t b[64], want[64];
    wbuf w;
    rlbi_wb_init(&w, b, sizeof b);
    rlbi_wb_array(&w, 3);
    rlbi_wb_u64(&w, 34);
    rlbi_wb_u64(&w, 4);
    rlbi_wb_u64(&w, 1280);
    size_t n = unhex("9322" "04cd0500", want);
    assert_int_equal(w.len, n);
    assert_memory_equal(b, want, n);
    rlbi_wb_init(&w, b, 3); /* overflow is reported, never written past cap */
    rlbi_wb_f64(&w, 1.5);
    assert_true(w.overflow);
}

static void message_builder_and_accessors(void **state) {
    (void)state;
    uint8_t buf[128];
    rlb_msg m;
    rlb_msg_init(&m, buf, sizeof buf);
    rlb_msg_map(&m, 2);
    rlb_msg_key(&m, "linear");
    rlb_msg_map(&m, 2);
    rlb_msg_key(&m, "x");
    rlb_msg_f64(&m, 0.5);
    rlb_msg_key(&m, "n");
    rlb_msg_i64(&m, -7);
    rlb_msg_key(&m, "on");
    rlb_msg_bool(&m, true);
    int len = rlb_msg_end(&m);
    assert_true(len > 0);
    double x;
    int64_t i;
    bool on;
    assert_int_equal(rlb_msg_get_f64(buf, (size_t)len, "linear.x", &x), RLB_OK);
    assert_true(x == 0.5);
    assert_int_equal(rlb_msg_get_i64(buf, (size_t)len, "linear.n", &i), RLB_OK);
    assert_int_equal(i, -7);
    assert_int_equal(rlb_msg_get_bool(buf, (size_t)len, "on", &on), RLB_OK);
    assert_true(on);
    assert_int_equal(rlb_msg_get_f64(buf, (size_t)len, "linear.y", &x), RLB_E_NOVALUE);
    assert_int_equal(rlb_msg_get_bool(buf, (size_t)len, "linear.x", &on), RLB_E_TYPE);
    rlb_msg_init(&m, buf, 4);
    rlb_msg_key(&m, "too long for four bytes");
    assert_int_equal(rlb_msg_end(&m), RLB_E_TOOBIG);
}

static rlb_client *client_with(rlb_channel **pub, rlb_channel **queue, rlb_channel **latest,
                               void *storage, size_t storage_bytes) {
    rlb_config cfg;
    rlb_config_init(&cfg);
    rlb_client *c;
    assert_int_equal(rlb_client_new(&cfg, &c), RLB_OK);
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, "/x", "std_msgs/msg/Float64", "data");
    o.capacity = 4;
    o.storage = storage;
    o.storage_bytes = storage_bytes;
    assert_int_equal(rlb_publish(c, &o, pub), RLB_OK);
    o.storage = NULL;
    o.mode = RLB_QUEUE;
    assert_int_equal(rlb_subscribe(c, &o, queue), RLB_OK);
    o.mode = RLB_LATEST;
    assert_int_equal(rlb_subscribe(c, &o, latest), RLB_OK);
    return c;
}

static void rings_and_triple_buffer(void **state) {
    (void)state;
    rlb_channel *pub, *q, *l;
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, "/x", "std_msgs/msg/Float64", "data");
    o.capacity = 4;
    size_t need = rlb_channel_storage(&o);
    void *storage = malloc(need);
    rlb_client *c = client_with(&pub, &q, &l, storage, need);
    for (int i = 0; i < 4; i++) assert_int_equal(rlb_write_f64(pub, i), RLB_OK);
    assert_int_equal(rlb_write_f64(pub, 4), RLB_E_FULL); /* full: refused and counted */
    rlb_channel_stats st;
    rlb_channel_stats_get(pub, &st);
    assert_int_equal(st.pending, 4);
    assert_int_equal(st.dropped, 1);
    double v;
    assert_int_equal(rlb_read_f64(q, &v), RLB_E_NOVALUE);
    assert_int_equal(rlb_read_f64(l, &v), RLB_E_NOVALUE);
    uint8_t enc[9] = {0xcb};
    for (int i = 1; i <= 3; i++) {
        double d = i;
        uint64_t bits;
        memcpy(&bits, &d, 8);
        for (int j = 0; j < 8; j++) enc[1 + j] = (uint8_t)(bits >> (56 - 8 * j));
        assert_true(rlbi_chan_deliver(q, 0, enc, 9));
        assert_true(rlbi_chan_deliver(l, 0, enc, 9));
    }
    /* the queue returns every value in order, then the last one again, not new */
    for (int i = 1; i <= 3; i++) {
        assert_int_equal(rlb_read_f64(q, &v), RLB_NEW);
        assert_true(v == i);
    }
    assert_int_equal(rlb_read_f64(q, &v), 0);
    assert_true(v == 3);
    /* latest: the newest value once as new, then again as not new */
    assert_int_equal(rlb_read_f64(l, &v), RLB_NEW);
    assert_true(v == 3);
    assert_int_equal(rlb_read_f64(l, &v), 0);
    assert_true(v == 3);
    bool b;
    assert_int_equal(rlb_read_bool(l, &b), RLB_E_TYPE);
    assert_int_equal(rlb_write_f64(q, 1.0), RLB_E_INVAL); /* no writes on an incoming channel */
    rlb_close(c);
    free(storage);
}

static void bad_declarations_are_errors(void **state) {
    (void)state;
    rlb_config cfg;
    rlb_config_init(&cfg);
    rlb_client *c;
    assert_int_equal(rlb_client_new(&cfg, &c), RLB_OK);
    rlb_channel *ch;
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, "no-slash", "std_msgs/msg/Float64", "data");
    assert_int_equal(rlb_publish(c, &o, &ch), RLB_E_INVAL);
    rlb_channel_opts_init(&o, "/x", "std_msgs/msg/Float64", "data");
    o.flow = 1; /* flow on UDP: protocol.md 10.5 honours it only on TCP */
    assert_int_equal(rlb_subscribe(c, &o, &ch), RLB_E_INVAL);
    o.flow = -1;
    o.capacity = 0;
    assert_int_equal(rlb_publish(c, &o, &ch), RLB_E_INVAL);
    o.capacity = 8;
    o.redundancy = 2;
    o.transport = RLB_TCP; /* redundancy is a UDP policy (protocol.md 10.3) */
    assert_int_equal(rlb_publish(c, &o, &ch), RLB_E_INVAL);
    o.transport = RLB_UDP;
    o.redundancy = 17;
    assert_int_equal(rlb_publish(c, &o, &ch), RLB_E_INVAL);
    o.redundancy = 16;
    o.value_bytes = 100; /* 17 values of 100 bytes do not fit a datagram */
    assert_int_equal(rlb_publish(c, &o, &ch), RLB_E_INVAL);
    rlb_close(c);
    cfg.max_channels = 0;
    assert_int_equal(rlb_client_new(&cfg, &c), RLB_E_INVAL);
}

static void received_packets_of_section_14(void **state) {
    (void)state;
    rlb_config cfg;
    rlb_config_init(&cfg);
    rlb_client *c;
    assert_int_equal(rlb_client_new(&cfg, &c), RLB_OK);
    rlb_channel *ch[4];
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, "/x", "std_msgs/msg/Float64", "data");
    o.mode = RLB_QUEUE;
    for (int i = 0; i < 4; i++) assert_int_equal(rlb_subscribe(c, &o, &ch[i]), RLB_OK);
    rlb_debug_bind_all(c, 0x0123456789abcdefULL);
    uint8_t d[256];
    /* 14.10: a Bundle datagram, channel 3 seq 7 = 1.5, channel 4 seq 0 = -2.0 */
    size_t n = unhex("524201000123456789abcdef92209295080307cf17979cfe362a0000cb3ff8000000000000"
                     "95080400cf17979cfe362a0000cbc000000000000000", d);
    rlb_debug_feed_datagram(c, d, n);
    double v;
    assert_int_equal(rlb_read_f64(ch[2], &v), RLB_NEW);
    assert_true(v == 1.5);
    assert_int_equal(rlb_read_stamp(ch[2]), 1700000000000000000LL);
    assert_int_equal(rlb_read_f64(ch[3], &v), RLB_NEW);
    assert_true(v == -2.0);
    rlb_debug_feed_datagram(c, d, n); /* the same again: duplicates, nothing delivered */
    assert_int_equal(rlb_read_f64(ch[2], &v), 0);
    rlb_channel_stats st;
    rlb_channel_stats_get(ch[2], &st);
    assert_int_equal(st.duplicates, 1);
    d[11] ^= 1; /* another token: dropped before the body */
    rlb_debug_feed_datagram(c, d, n);
    /* 14.5: a Batch frame on channel 2, seq 10 and 11, as a TCP stream cut in two */
    n = unhex("524201000000002a9509020a92cf17979cfe362a0000cf17979cfe3639424092cb3fd0000000000000"
              "cbc000000000000000", d);
    rlb_debug_feed_stream(c, d, 7);
    assert_int_equal(rlb_read_f64(ch[1], &v), RLB_E_NOVALUE);
    rlb_debug_feed_stream(c, d + 7, n - 7);
    assert_int_equal(rlb_read_f64(ch[1], &v), RLB_NEW);
    assert_true(v == 0.25);
    assert_int_equal(rlb_read_f64(ch[1], &v), RLB_NEW);
    assert_true(v == -2.0);
    /* a gap: seq 15 after 11 counts 3 lost */
    n = unhex("5242010000000016950802" "0f" "cf17979cfe362a0000cb3ff0000000000000", d);
    rlb_debug_feed_stream(c, d, n);
    rlb_channel_stats_get(ch[1], &st);
    assert_int_equal(st.lost, 3);
    /* malformed bodies are counted, never delivered: a Batch whose lengths differ, junk */
    uint64_t before = rlb_debug_malformed(c);
    n = unhex("5242010000000009" "950902149100920102", d);
    rlb_debug_feed_stream(c, d, n);
    n = unhex("5242010000000003c1c1c1", d);
    rlb_debug_feed_stream(c, d, n);
    assert_int_equal(rlb_debug_malformed(c), before + 2);
    assert_int_equal(rlb_read_f64(ch[1], &v), RLB_NEW); /* only the seq-15 value */
    assert_true(v == 1.0);
    assert_int_equal(rlb_read_f64(ch[1], &v), 0);
    /* a heartbeat echoing our clock 5 ms ago: one RTT sample of at least 5 ms */
    assert_int_equal(rlb_rtt_ns(c), -1);
    wbuf w;
    rlbi_wb_init(&w, d + 8, sizeof d - 8);
    rlbi_wb_array(&w, 3);
    rlbi_wb_u64(&w, 10);
    rlbi_wb_i64(&w, 1);
    rlbi_wb_i64(&w, rlb_mono_ns() - 5000000);
    n = unhex("5242010000000000", d);
    d[7] = (uint8_t)w.len;
    rlb_debug_feed_stream(c, d, 8 + w.len);
    assert_true(rlb_rtt_ns(c) >= 5000000);
    assert_true(rlb_rtt_ns(c) < 5000000000LL);
    rlb_close(c);
}

int main(void) {
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(batch_of_section_14_5),
        cmocka_unit_test(truncated_and_hostile_input_is_an_error),
        cmocka_unit_test(encoder_matches_section_14),
        cmocka_unit_test(message_builder_and_accessors),
        cmocka_unit_test(rings_and_triple_buffer),
        cmocka_unit_test(bad_declarations_are_errors),
        cmocka_unit_test(received_packets_of_section_14),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
