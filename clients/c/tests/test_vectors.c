/* protocol.md 16.6: the test vectors of a pre-shared-key session, byte for byte. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include <cmocka.h>
#include <sodium.h>

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

static void assert_hex(const uint8_t *got, size_t len, const char *want) {
    uint8_t w[512];
    size_t n = unhex(want, w);
    assert_int_equal(len, n);
    assert_memory_equal(got, w, n);
}

static uint8_t K[32], NC[16], NS[16];

static void seq_bytes(uint8_t *b, size_t n, uint8_t first) {
    for (size_t i = 0; i < n; i++) b[i] = (uint8_t)(first + i);
}

static int setup(void **state) {
    (void)state;
    if (sodium_init() < 0) return -1;
    seq_bytes(K, 32, 0);
    seq_bytes(NC, 16, 0);
    seq_bytes(NS, 16, 0x10);
    return 0;
}

static void transcript_and_proofs(void **state) {
    (void)state;
    uint8_t t[128], p[32];
    size_t tl = rlb_transcript("robot", NC, NS, t, sizeof t);
    assert_hex(t, tl, "000200010005726f626f740010000102030405060708090a0b0c0d0e0f0010101112131415161718191a1b1c1d1e1f");
    rlb_proof(K, 32, "server-proof", t, tl, p);
    assert_hex(p, 32, "9dc12af136812194be8f595ece20b55f408efd8cd7124bf565600709a19634d3");
    rlb_proof(K, 32, "client-proof", t, tl, p);
    assert_hex(p, 32, "85cf5f9e141cc406726f58fc0cf8a01cce50b2b07cd05151eae94f147a1ec3c0");
}

static void session_keys(void **state) {
    (void)state;
    uint8_t t[128];
    size_t tl = rlb_transcript("robot", NC, NS, t, sizeof t);
    rlb_keys k;
    rlb_derive(K, 32, NC, NS, t, tl, &k);
    assert_hex(k.kc2s, 32, "14144b1c4dd40ef5046b844e78cb0b3d8b8a6050505af4e9ec80e700ee5fc2f0");
    assert_hex(k.ks2c, 32, "d6ab44219f0037be86b5ae5ea028c0ede8e0e339f091525379e5ed2fd1520fd1");
    assert_hex(k.rc2s, 32, "fb98ddb28c838bce45e1d675911cd6d5ec5c5a66560f43bfbc7c1b20ddaba5fa");
    assert_hex(k.rs2c, 32, "a0df019c6c961104114636fcb3ad3714a1cdbd19517d91e9350467a42c4e6ee8");
}

static void sealed_datagram(void **state) {
    (void)state;
    uint8_t t[128], d[128];
    size_t tl = rlb_transcript("robot", NC, NS, t, sizeof t);
    rlb_keys k;
    rlb_derive(K, 32, NC, NS, t, tl, &k);
    /* header (flags SEALED), token, counter 1, then the Value body encoded by the library */
    size_t n = unhex("52420101" "0102030405060708" "0000000000000001", d);
    wbuf w;
    rlbi_wb_init(&w, d + n, sizeof d - n);
    rlbi_wb_array(&w, 5);
    rlbi_wb_u64(&w, 8);
    rlbi_wb_u64(&w, 1);
    rlbi_wb_u64(&w, 0);
    rlbi_wb_i64(&w, 0);
    rlbi_wb_f64(&w, 1.5);
    assert_hex(d + n, w.len, "9508010000cb3ff8000000000000");
    rlb_seal(k.kc2s, 1, d, 20, d + 20, w.len, d + 20 + w.len);
    size_t total = 20 + w.len + 16;
    assert_hex(d, total, "5242010101020304050607080000000000000001f3420fb5b98aa532528e7aa471cebef90b44a30a5f20f14edb45bce71310");
    /* and it opens again under the same key, not under the other direction's */
    uint8_t copy[128];
    memcpy(copy, d, total);
    assert_false(rlb_open(k.ks2c, 1, copy, 20, copy + 20, w.len, copy + 20 + w.len));
    assert_true(rlb_open(k.kc2s, 1, d, 20, d + 20, w.len, d + 20 + w.len));
    assert_hex(d + 20, w.len, "9508010000cb3ff8000000000000");
}

static void sealed_record(void **state) {
    (void)state;
    uint8_t t[128], r[128];
    size_t tl = rlb_transcript("robot", NC, NS, t, sizeof t);
    rlb_keys k;
    rlb_derive(K, 32, NC, NS, t, tl, &k);
    size_t m = unhex("5242010000000007960a0100000000", r + 8);
    unhex("524201010000001f", r); /* header: SEALED, length m + 16 */
    rlb_seal(k.rc2s, 0, r, 8, r + 8, m, r + 8 + m);
    assert_hex(r, 8 + m + 16, "524201010000001fca15266c928933a65cc37cf162090c99662dc5a776da74b09b203704f7b3df");
}

static void tls_datagram_keys(void **state) {
    (void)state;
    uint8_t s[32];
    seq_bytes(s, 32, 0x40);
    rlb_keys k;
    rlb_derive_tls(s, 32, 0x0102030405060708ULL, &k);
    assert_hex(k.kc2s, 32, "5a58f53f05a892fb2469d003b250bdae04f893c757df3ebcbbdf832bcce033ed");
    assert_hex(k.ks2c, 32, "9cf139d34df410d8571444e72a9dacd9d2ec3664924dc29a1e2f4bafc7d032c7");
}

int main(void) {
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(transcript_and_proofs),
        cmocka_unit_test(session_keys),
        cmocka_unit_test(sealed_datagram),
        cmocka_unit_test(sealed_record),
        cmocka_unit_test(tls_datagram_keys),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}
