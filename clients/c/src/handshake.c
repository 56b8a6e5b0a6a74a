/*
 * Opening a session (protocol.md 8.1, 8.2, 16.1): Hello, with a key the AuthChallenge /
 * AuthProof exchange, then ConnectAck. Over TCP the frames are read from the stream, the
 * ConnectAck of a keyed session being the first sealed record; over UDP (a UDP-only session)
 * the Hello and the proof go with token 0, unsealed, repeated every 200 ms until answered, and
 * a keyed ConnectAck arrives sealed with the new token in its header.
 */
#include <errno.h>
#include <poll.h>
#include <sodium.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>

#include "conn.h"

#define RESEND_NS 200000000 /* the reference client repeats a UDP Hello every 200 ms */

typedef struct hs {
    uint8_t nc[16];
    bool keyed, challenged;
    uint8_t proof[32];
} hs;

static void enc_hello(rlb_client *c, const hs *h, wbuf *w) {
    rlbi_wb_array(w, 4);
    rlbi_wb_u64(w, T_HELLO);
    rlbi_wb_u64(w, RLB_PROTOCOL_VERSION);
    rlbi_wb_str(w, c->name, strlen(c->name));
    rlbi_wb_bin(w, h->nc, h->keyed ? 16 : 0);
}

static void enc_proof(const hs *h, wbuf *w) {
    rlbi_wb_array(w, 2);
    rlbi_wb_u64(w, T_PROOF);
    rlbi_wb_bin(w, h->proof, 32);
}

static void enc_refusal(const hs *h, wbuf *w) {
    (void)h;
    rlbi_wb_array(w, 3);
    rlbi_wb_u64(w, T_DISCONNECT);
    rlbi_wb_u64(w, 21);
    rlbi_wb_str(w, "server proof wrong", 18);
}

/* ConnectError: the event, and the status rlb_connect returns. */
static rlb_status refused(rlb_client *c, mp_cur *m) {
    uint64_t code = 0;
    const char *reason = "";
    uint32_t rl = 0;
    char text[256];
    if (rlbi_mp_u64(m, &code)) rlbi_mp_str(m, &reason, &rl);
    snprintf(text, sizeof text, "%.*s", (int)(rl < 255 ? rl : 255), reason);
    rlb_emit(c, RLB_EV_DISCONNECT, (int)code, 0, text);
    return code == 21 ? RLB_E_AUTH : RLB_E_REFUSED;
}

/* AuthChallenge: checks the server's proof before ours is sent (16.1) and derives the keys.
 * RLB_OK with h->proof ready, RLB_E_AUTH when the server does not know our key. */
static rlb_status challenge(rlb_client *c, hs *h, mp_cur *m) {
    const uint8_t *ns, *ps;
    uint32_t nl, pl;
    uint8_t t[300], mine[32];
    if (!h->keyed || !rlbi_mp_bin(m, &ns, &nl) || nl != 16 || !rlbi_mp_bin(m, &ps, &pl) || pl != 32)
        return RLB_E_AUTH;
    size_t tlen = rlb_transcript(c->name, h->nc, ns, t, sizeof t);
    rlb_proof(c->psk, c->psk_len, "server-proof", t, tlen, mine);
    if (sodium_memcmp(mine, ps, 32) != 0) return RLB_E_AUTH;
    rlb_derive(c->psk, c->psk_len, h->nc, ns, t, tlen, &c->conn->keys);
    rlb_proof(c->psk, c->psk_len, "client-proof", t, tlen, h->proof);
    h->challenged = true;
    return RLB_OK;
}

/* ConnectAck: the token, the heartbeat and the watchdog of the session; over TLS without a
 * key, the secret the datagram keys derive from (16.4). */
static rlb_status take_ack(rlb_conn *k, mp_cur *m, bool tls_keys) {
    uint64_t session, token, hb, to;
    uint32_t nl;
    if (!rlbi_mp_u64(m, &session) || !rlbi_mp_u64(m, &token) || !rlbi_mp_u64(m, &hb) ||
        !rlbi_mp_u64(m, &to) || !rlbi_mp_array(m, &nl) || token == 0 || hb == 0)
        return RLB_E_CONNECT;
    for (uint32_t i = 0; i < nl; i++)
        if (!rlbi_mp_skip(m)) return RLB_E_CONNECT;
    k->token = token;
    k->hb_ms = (uint32_t)hb;
    k->timeout_ms = (uint32_t)to;
    if (tls_keys) {
        const uint8_t *secret;
        uint32_t len;
        if (!rlbi_mp_bin(m, &secret, &len) || len == 0) return RLB_E_AUTH;
        rlb_derive_tls(secret, len, token, &k->keys);
        k->sealed = true;
    }
    return RLB_OK;
}

static void start(rlb_client *c, hs *h) {
    memset(h, 0, sizeof *h);
    h->keyed = c->psk_len > 0;
    if (h->keyed) randombytes_buf(h->nc, sizeof h->nc);
}

/* -- over TCP ----------------------------------------------------------------------------- */

/* Waits for the next TCP frame of the handshake; NULL on timeout or a broken connection. */
static const uint8_t *next(rlb_conn *k, int64_t deadline, size_t *len) {
    for (;;) {
        bool bad;
        const uint8_t *f = rlbi_tcp_next_frame(k, len, &bad);
        if (f != NULL) return f;
        if (bad) return NULL;
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if (left <= 0) return NULL;
        struct pollfd p = {k->tcp, POLLIN, 0};
        if (!rlbi_tls_pending(k) && poll(&p, 1, (int)left) < 0 && errno != EINTR) return NULL;
        if (!rlbi_tcp_read(k)) { /* the stream ended or broke: what is buffered is all */
            f = rlbi_tcp_next_frame(k, len, &bad);
            return bad ? NULL : f;
        }
    }
}

rlb_status rlbi_handshake_tcp(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    hs h;
    start(c, &h);
    wbuf w;
    rlbi_tcp_frame_begin(k, &w);
    enc_hello(c, &h, &w);
    rlbi_tcp_frame_end(k, &w);
    if (!rlbi_tcp_flush_blocking(k, deadline)) return RLB_E_CONNECT;
    for (;;) {
        size_t len;
        const uint8_t *f = next(k, deadline, &len);
        if (f == NULL && k->tls_error[0]) { /* TLS ended it: the server refused us */
            char text[200];
            snprintf(text, sizeof text, "TLS: the server ended the connection: %s",
                     k->tls_error);
            rlb_emit(c, RLB_EV_DISCONNECT, 21, 0, text);
            return RLB_E_AUTH;
        }
        if (f == NULL) return RLB_E_CONNECT;
        mp_cur m;
        uint32_t n;
        uint64_t tag;
        rlbi_mp_init(&m, f, len);
        if (!rlbi_mp_array(&m, &n) || !rlbi_mp_u64(&m, &tag)) return RLB_E_CONNECT;
        if (tag == T_CONNERR) return refused(c, &m);
        if (tag == T_CHALLENGE) {
            if (challenge(c, &h, &m) != RLB_OK) {
                if (h.keyed) { /* a server without our key: say why, send no proof */
                    rlbi_tcp_frame_begin(k, &w);
                    enc_refusal(&h, &w);
                    rlbi_tcp_frame_end(k, &w);
                    rlbi_tcp_flush_blocking(k, deadline);
                }
                return RLB_E_AUTH;
            }
            rlbi_tcp_frame_begin(k, &w);
            enc_proof(&h, &w);
            rlbi_tcp_frame_end(k, &w);
            if (!rlbi_tcp_flush_blocking(k, deadline)) return RLB_E_CONNECT;
            k->sealed = true; /* datagrams under the key's Kc2s/Ks2c (16.3) */
            if (k->ssl) continue; /* inside TLS the stream is not sealed again (16.4) */
            /* From the ConnectAck on the server sends records: what follows is one. */
            size_t rest = k->in_len - k->in_off;
            if (rest > RECORD_MAX + 32) return RLB_E_CONNECT;
            memcpy(k->rec, k->in + k->in_off, rest);
            k->rec_len = rest;
            k->in_off = k->in_len = 0;
            k->records = true;
            if (!rlbi_tcp_open_records(k)) return RLB_E_AUTH;
            continue;
        }
        if (tag == T_ACK) {
            if (h.keyed && !h.challenged) return RLB_E_AUTH; /* no downgrade (16.1) */
            return take_ack(k, &m, k->ssl != NULL && !h.keyed);
        }
        /* anything else before the ack is ignored */
    }
}

/* -- over UDP ----------------------------------------------------------------------------- */

static void send_token0(rlb_conn *k, rlb_client *c, const hs *h, void (*enc)(const hs *, wbuf *)) {
    wbuf w;
    rlbi_wb_init(&w, k->dg_tx + UDP_HDR, DGRAM_MAX - UDP_HDR);
    if (enc) enc(h, &w);
    else enc_hello(c, h, &w);
    if (!w.overflow) rlbi_udp_send_as(k, w.len, 0, false);
}

/* One datagram of the handshake: RLB_OK when it was the ConnectAck, 1 to go on, or an error. */
static int udp_answer(rlb_client *c, hs *h, uint8_t *d, size_t n, int64_t *resend) {
    rlb_conn *k = c->conn;
    if (n < UDP_HDR || d[0] != 'R' || d[1] != 'B' || d[2] != RLB_PROTOCOL_VERSION) return 1;
    uint64_t token = 0;
    for (int i = 0; i < 8; i++) token = token << 8 | d[4 + i];
    const uint8_t *body = d + UDP_HDR;
    size_t len = n - UDP_HDR;
    if (token != 0 && h->keyed) { /* the ConnectAck of a keyed session is already sealed */
        if (!h->challenged || !(d[3] & F_SEALED) || n < 36) return 1;
        uint64_t ctr = 0;
        for (int i = 0; i < 8; i++) ctr = ctr << 8 | d[12 + i];
        len = n - 36;
        if (!rlb_open(k->keys.ks2c, ctr, d, 20, d + 20, len, d + 20 + len) ||
            !rlbi_udp_replay_ok(k, ctr))
            return 1;
        body = d + 20;
    } else if (d[3] & F_SEALED) {
        return 1;
    }
    mp_cur m;
    uint32_t cnt;
    uint64_t tag;
    rlbi_mp_init(&m, body, len);
    if (!rlbi_mp_array(&m, &cnt) || !rlbi_mp_u64(&m, &tag)) return 1;
    if (token == 0 && tag == T_CONNERR) return refused(c, &m);
    if (token == 0 && tag == T_CHALLENGE && !h->challenged) {
        if (challenge(c, h, &m) != RLB_OK) {
            if (h->keyed) send_token0(k, c, h, enc_refusal);
            return RLB_E_AUTH;
        }
        *resend = 0; /* the proof goes at once */
        return 1;
    }
    if (token != 0 && tag == T_ACK) {
        if (h->keyed && !h->challenged) return RLB_E_AUTH; /* no downgrade (16.1) */
        rlb_status rc = take_ack(k, &m, false);
        if (rc == RLB_OK && k->token != token) return RLB_E_CONNECT;
        if (rc == RLB_OK) k->sealed = h->keyed;
        return rc;
    }
    return 1;
}

rlb_status rlbi_handshake_udp(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    hs h;
    start(c, &h);
    k->token = 0;
    int64_t resend = 0;
    for (;;) {
        int64_t now = rlb_mono_ns();
        if (now >= deadline) return RLB_E_CONNECT;
        if (now >= resend) {
            send_token0(k, c, &h, h.challenged ? enc_proof : NULL);
            resend = now + RESEND_NS;
        }
        int64_t until = (resend < deadline ? resend : deadline) - now;
        struct pollfd p = {k->udp, POLLIN, 0};
        if (poll(&p, 1, (int)(until / 1000000) + 1) < 0 && errno != EINTR) return RLB_E_IO;
        for (int i = 0; i < 64; i++) {
            ssize_t n = recv(k->udp, k->dg_rx, RX_DGRAM, MSG_DONTWAIT);
            if (n < 0) break;
            int rc = udp_answer(c, &h, k->dg_rx, (size_t)n, &resend);
            if (rc != 1) return (rlb_status)rc;
        }
    }
}
