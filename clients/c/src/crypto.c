/*
 * Pre-shared-key sessions (protocol.md section 16) on libsodium: the transcript, the two
 * HMAC-SHA256 proofs, HKDF-SHA256 (written out over libsodium's HMAC: Debian 12's libsodium
 * 1.0.18 has no HKDF) and ChaCha20-Poly1305 IETF with the counter nonce.
 */
#include <sodium.h>
#include <string.h>

#include "internal.h"

static const char LABEL[] = "rlbridge-psk-v1"; /* + the NUL: 16 bytes */
static const char INFO[] = "rlbridge-keys-v1"; /* + the NUL: 17 bytes */

static size_t lp(uint8_t *out, size_t at, size_t cap, const void *x, size_t n) {
    if (at + 2 + n > cap) return cap + 1;
    out[at] = (uint8_t)(n >> 8);
    out[at + 1] = (uint8_t)n;
    memcpy(out + at + 2, x, n);
    return at + 2 + n;
}

size_t rlb_transcript(const char *name, const uint8_t nc[16], const uint8_t ns[16],
                      uint8_t *out, size_t cap) {
    static const uint8_t version[2] = {0, RLB_PROTOCOL_VERSION};
    size_t at = lp(out, 0, cap, version, 2);
    if (at <= cap) at = lp(out, at, cap, name, strlen(name));
    if (at <= cap) at = lp(out, at, cap, nc, 16);
    if (at <= cap) at = lp(out, at, cap, ns, 16);
    return at <= cap ? at : 0;
}

void rlb_proof(const uint8_t *key, size_t key_len, const char *label, const uint8_t *t,
               size_t t_len, uint8_t out[32]) {
    crypto_auth_hmacsha256_state st;
    crypto_auth_hmacsha256_init(&st, key, key_len);
    crypto_auth_hmacsha256_update(&st, (const uint8_t *)LABEL, sizeof LABEL);
    crypto_auth_hmacsha256_update(&st, (const uint8_t *)label, strlen(label) + 1);
    crypto_auth_hmacsha256_update(&st, t, t_len);
    crypto_auth_hmacsha256_final(&st, out);
}

/* HKDF-SHA256 (RFC 5869) with info = INFO || info, 128 bytes: the four keys of 16.2. */
static void hkdf(const uint8_t *ikm, size_t ikm_len, const uint8_t *salt, size_t salt_len,
                 const uint8_t *info, size_t info_len, rlb_keys *keys) {
    uint8_t prk[32], block[32], okm[128];
    crypto_auth_hmacsha256_state st; /* extract: PRK = HMAC(salt, IKM); an empty salt is the
                                        same key as HashLen zeros */
    crypto_auth_hmacsha256_init(&st, salt, salt_len);
    crypto_auth_hmacsha256_update(&st, ikm, ikm_len);
    crypto_auth_hmacsha256_final(&st, prk);
    size_t have = 0; /* expand: T(i) = HMAC(PRK, T(i-1) || info || i) */
    for (uint8_t i = 1; have < sizeof okm; i++) {
        crypto_auth_hmacsha256_init(&st, prk, sizeof prk);
        if (i > 1) crypto_auth_hmacsha256_update(&st, block, sizeof block);
        crypto_auth_hmacsha256_update(&st, (const uint8_t *)INFO, sizeof INFO);
        crypto_auth_hmacsha256_update(&st, info, info_len);
        crypto_auth_hmacsha256_update(&st, &i, 1);
        crypto_auth_hmacsha256_final(&st, block);
        memcpy(okm + have, block, sizeof block);
        have += sizeof block;
    }
    memcpy(keys->kc2s, okm, 32);
    memcpy(keys->ks2c, okm + 32, 32);
    memcpy(keys->rc2s, okm + 64, 32);
    memcpy(keys->rs2c, okm + 96, 32);
    sodium_memzero(okm, sizeof okm);
    sodium_memzero(prk, sizeof prk);
    sodium_memzero(block, sizeof block);
}

void rlb_derive(const uint8_t *key, size_t key_len, const uint8_t nc[16], const uint8_t ns[16],
                const uint8_t *t, size_t t_len, rlb_keys *keys) {
    uint8_t salt[32];
    memcpy(salt, nc, 16);
    memcpy(salt + 16, ns, 16);
    hkdf(key, key_len, salt, sizeof salt, t, t_len, keys);
}

void rlb_derive_tls(const uint8_t *secret, size_t len, uint64_t token, rlb_keys *keys) {
    uint8_t info[12] = {'t', 'l', 's', 0};
    for (int i = 0; i < 8; i++) info[4 + i] = (uint8_t)(token >> (56 - 8 * i));
    hkdf(secret, len, (const uint8_t *)"", 0, info, sizeof info, keys);
}

static void nonce_of(uint64_t counter, uint8_t nonce[12]) {
    memset(nonce, 0, 4);
    for (int i = 0; i < 8; i++) nonce[4 + i] = (uint8_t)(counter >> (56 - 8 * i));
}

void rlb_seal(const uint8_t key[32], uint64_t counter, const uint8_t *aad, size_t aad_len,
              uint8_t *text, size_t len, uint8_t tag[16]) {
    uint8_t nonce[12];
    nonce_of(counter, nonce);
    unsigned long long tag_len = 16;
    crypto_aead_chacha20poly1305_ietf_encrypt_detached(text, tag, &tag_len, text, len, aad,
                                                       aad_len, NULL, nonce, key);
}

bool rlb_open(const uint8_t key[32], uint64_t counter, const uint8_t *aad, size_t aad_len,
              uint8_t *text, size_t len, const uint8_t tag[16]) {
    uint8_t nonce[12];
    nonce_of(counter, nonce);
    return crypto_aead_chacha20poly1305_ietf_decrypt_detached(text, NULL, text, len, tag, aad,
                                                              aad_len, nonce, key) == 0;
}
