/* UDP datagrams: the header, the seal and its replay window (protocol.md 3, 16.3). */
#include <string.h>
#include <sys/socket.h>

#include "conn.h"

/* -- UDP output -------------------------------------------------------------------------- */

size_t rlbi_udp_body_at(const rlb_conn *k) { return UDP_HDR + (k->sealed ? 8u : 0u); }

size_t rlbi_udp_body_cap(const rlb_conn *k) {
    return DGRAM_MAX - UDP_HDR - (k->sealed ? SEAL_DGRAM : 0u);
}

/* Sends the body already written at rlbi_udp_body_at(k) in dg_tx. */
void rlbi_udp_send(rlb_conn *k, size_t body_len) {
    rlbi_udp_send_as(k, body_len, k->token, k->sealed);
}

/* The handshake's datagrams: token 0, flags 0, never sealed (protocol.md 3, 16.1). */
void rlbi_udp_send_as(rlb_conn *k, size_t body_len, uint64_t token, bool sealed) {
    uint8_t *d = k->dg_tx;
    d[0] = 'R', d[1] = 'B', d[2] = RLB_PROTOCOL_VERSION;
    d[3] = token == 0 ? 0 : F_BUNDLES | (sealed ? F_SEALED : 0);
    for (int i = 0; i < 8; i++) d[4 + i] = (uint8_t)(token >> (56 - 8 * i));
    size_t len = UDP_HDR + body_len;
    if (sealed) {
        uint64_t ctr = ++k->dgram_tx;
        for (int i = 0; i < 8; i++) d[12 + i] = (uint8_t)(ctr >> (56 - 8 * i));
        rlb_seal(k->keys.kc2s, ctr, d, 20, d + 20, body_len, d + 20 + body_len);
        len = 20 + body_len + 16;
    }
    (void)send(k->udp, d, len, MSG_DONTWAIT); /* UDP: a full socket buffer is a lost datagram */
}

/* -- UDP input ----------------------------------------------------------------------------- */

bool rlbi_udp_replay_ok(rlb_conn *k, uint64_t ctr) {
    if (ctr == 0) return false;
    if (ctr > k->replay_top) {
        uint64_t shift = ctr - k->replay_top;
        if (shift >= 1024) {
            memset(k->replay_bits, 0, sizeof k->replay_bits);
        } else {
            for (uint64_t s = 0; s < shift; s++) { /* slide: bit i = counter top - i */
                for (int w = 15; w > 0; w--)
                    k->replay_bits[w] = k->replay_bits[w] << 1 | k->replay_bits[w - 1] >> 63;
                k->replay_bits[0] <<= 1;
            }
        }
        k->replay_top = ctr;
        k->replay_bits[0] |= 1;
        return true;
    }
    uint64_t back = k->replay_top - ctr;
    if (back >= 1024) return false;
    uint64_t bit = 1ULL << (back % 64);
    if (k->replay_bits[back / 64] & bit) return false;
    k->replay_bits[back / 64] |= bit;
    return true;
}

/* One received datagram: header, token, seal, then the body (protocol.md 3, 16.3). */
void rlbi_udp_datagram(rlb_client *c, uint8_t *d, size_t n) {
    rlb_conn *k = c->conn;
    if (n < UDP_HDR || d[0] != 'R' || d[1] != 'B' || d[2] != RLB_PROTOCOL_VERSION) {
        rlbi_conn_malformed(k);
        return;
    }
    uint64_t token = 0;
    for (int j = 0; j < 8; j++) token = token << 8 | d[4 + j];
    if (token != k->token) return;
    const uint8_t *body = d + UDP_HDR;
    size_t len = n - UDP_HDR;
    if (k->sealed) {
        if (!(d[3] & F_SEALED) || n < 36) return;
        uint64_t ctr = 0;
        for (int j = 0; j < 8; j++) ctr = ctr << 8 | d[12 + j];
        len = n - 36;
        if (!rlb_open(k->keys.ks2c, ctr, d, 20, d + 20, len, d + 20 + len)) return;
        if (!rlbi_udp_replay_ok(k, ctr)) return;
        body = d + 20;
    }
    rlbi_conn_packet(c, body, len, false);
}

void rlbi_udp_read(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (int i = 0; i < 256 && k->udp >= 0 && k->up; i++) {
        ssize_t n = recv(k->udp, k->dg_rx, RX_DGRAM, MSG_DONTWAIT);
        if (n < 0) return;
        rlbi_udp_datagram(c, k->dg_rx, (size_t)n);
    }
}

