/*
 * The I/O side: one session at a time over a TCP connection (the control transport) and a
 * connected UDP socket, following docs/protocol.md. Everything here runs on the thread of
 * rlb_connect / rlb_start / rlb_spin_once, never on the real-time side; its buffers are
 * allocated once by conn_new.
 */
#include <errno.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sodium.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "internal.h"

enum {
    T_HELLO = 1, T_ACK = 2, T_CONNERR = 3, T_TOPIC = 4, T_TOPICACK = 5, T_TOPICERR = 6,
    T_VALUE = 8, T_BATCH = 9, T_HEARTBEAT = 10, T_DISCONNECT = 11, T_ERROR = 12, T_STATS = 13,
    T_CHALLENGE = 14, T_PROOF = 15, T_BUNDLE = 32, T_CREDIT = 34, T_LOSS = 35
};

#define F_SEALED 0x01
#define F_BUNDLES 0x80
#define UDP_HDR 12
#define SEAL_DGRAM 24
#define DGRAM_MAX 1400     /* what we send: below the path MTU (protocol.md section 3) */
#define RX_DGRAM 65536
#define RECORD_MAX 65536   /* plaintext bytes per sealed record (16.5) */
#define TCP_BATCH 1024     /* values per Batch frame we send (below max_batch) */
#define ROUND_DGRAMS 64    /* datagrams per send round, so that one spin stays bounded */

struct rlb_conn {
    int tcp, udp;
    bool up;
    uint64_t token;
    uint32_t hb_ms, timeout_ms;
    bool sealed;
    rlb_keys keys;
    uint64_t dgram_tx, rec_tx, rec_rx;
    uint64_t replay_top, replay_bits[16]; /* 1024 counters below replay_top */
    size_t cap;                          /* of out / in */
    uint8_t *out, *wire, *in, *rec;
    size_t out_len, wire_off, wire_len, wire_cap, in_off, in_len, rec_len, skip;
    uint8_t *dg_tx, *dg_rx;
    int64_t last_rx, last_hb;
    int64_t peer_sent, peer_rx, peer_wall, peer_wall_rx;
    int64_t retry_at;
    uint32_t backoff_ms;
    bool closed;
    size_t rr; /* round-robin start among UDP channels */
    uint64_t malformed;
};

rlb_status conn_new(rlb_client *c) {
    rlb_conn *k = calloc(1, sizeof *k);
    if (k == NULL) return RLB_E_NOMEM;
    k->tcp = k->udp = -1;
    k->cap = c->cfg.tcp_buffer;
    k->wire_cap = k->cap + (k->cap / RECORD_MAX + 1) * 24;
    k->out = malloc(k->wire_cap);
    k->wire = malloc(k->wire_cap);
    k->in = malloc(k->cap);
    k->rec = malloc(RECORD_MAX + 24 + 8);
    k->dg_tx = malloc(DGRAM_MAX + 64);
    k->dg_rx = malloc(RX_DGRAM);
    if (!k->out || !k->wire || !k->in || !k->rec || !k->dg_tx || !k->dg_rx) {
        free(k->out), free(k->wire), free(k->in), free(k->rec), free(k->dg_tx), free(k->dg_rx);
        free(k);
        return RLB_E_NOMEM;
    }
    k->backoff_ms = c->cfg.backoff_initial_ms;
    c->conn = k;
    return RLB_OK;
}

static void close_sockets(rlb_conn *k) {
    if (k->tcp >= 0) close(k->tcp);
    if (k->udp >= 0) close(k->udp);
    k->tcp = k->udp = -1;
    k->up = false;
    k->sealed = false;
    sodium_memzero(&k->keys, sizeof k->keys);
}

void conn_free(rlb_client *c) {
    rlb_conn *k = c->conn;
    if (k == NULL) return;
    close_sockets(k);
    free(k->out), free(k->wire), free(k->in), free(k->rec), free(k->dg_tx), free(k->dg_rx);
    free(k);
    c->conn = NULL;
}

static size_t unsent_k(const rlb_conn *k) { return k->out_len + (k->wire_len - k->wire_off); }

size_t conn_unsent(rlb_client *c) { return unsent_k(c->conn); }

static rlb_channel *channel_of(rlb_client *c, uint64_t id) {
    if (id == 0 || id > c->n_channels) return NULL;
    return c->channels[id - 1];
}

/* -- TCP output -------------------------------------------------------------------------- */

/* Starts a frame: the body is written into w; frame_end commits it (false: no room). */
static void frame_begin(rlb_conn *k, wbuf *w) {
    size_t room = k->cap > k->out_len + 8 ? k->cap - k->out_len - 8 : 0;
    wb_init(w, k->out + k->out_len + 8, room);
    if (room == 0) w->overflow = true;
}

static bool frame_end(rlb_conn *k, const wbuf *w) {
    if (w->overflow) return false;
    uint8_t *h = k->out + k->out_len;
    h[0] = 'R', h[1] = 'B', h[2] = RLB_PROTOCOL_VERSION, h[3] = 0;
    h[4] = (uint8_t)(w->len >> 24), h[5] = (uint8_t)(w->len >> 16);
    h[6] = (uint8_t)(w->len >> 8), h[7] = (uint8_t)w->len;
    k->out_len += 8 + w->len;
    return true;
}

/* Moves the pending frames into the wire buffer (as sealed records on a keyed session). */
static void stage(rlb_conn *k) {
    if (k->wire_off < k->wire_len || k->out_len == 0) return;
    if (!k->sealed) {
        uint8_t *t = k->wire;
        k->wire = k->out;
        k->out = t;
        k->wire_len = k->out_len;
    } else {
        size_t at = 0, pos = 0;
        while (pos < k->out_len) {
            size_t m = k->out_len - pos < RECORD_MAX ? k->out_len - pos : RECORD_MAX;
            uint8_t *h = k->wire + at;
            uint32_t len = (uint32_t)m + 16;
            h[0] = 'R', h[1] = 'B', h[2] = RLB_PROTOCOL_VERSION, h[3] = F_SEALED;
            h[4] = (uint8_t)(len >> 24), h[5] = (uint8_t)(len >> 16);
            h[6] = (uint8_t)(len >> 8), h[7] = (uint8_t)len;
            memcpy(h + 8, k->out + pos, m);
            rlb_seal(k->keys.rc2s, k->rec_tx++, h, 8, h + 8, m, h + 8 + m);
            at += 8 + m + 16;
            pos += m;
        }
        k->wire_len = at;
    }
    k->wire_off = 0;
    k->out_len = 0;
}

/* Writes what the socket takes now; false when the connection broke. */
static bool tcp_flush(rlb_conn *k) {
    for (int i = 0; i < 4; i++) {
        stage(k);
        if (k->wire_off >= k->wire_len) return true;
        ssize_t n = send(k->tcp, k->wire + k->wire_off, k->wire_len - k->wire_off,
                         MSG_NOSIGNAL | MSG_DONTWAIT);
        if (n < 0) return errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR;
        k->wire_off += (size_t)n;
        if (k->wire_off == k->wire_len) k->wire_off = k->wire_len = 0;
    }
    return true;
}

static bool tcp_flush_blocking(rlb_conn *k, int64_t deadline) {
    while (unsent_k(k) > 0) {
        if (!tcp_flush(k)) return false;
        if (k->out_len == 0 && k->wire_off >= k->wire_len) break;
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if (left <= 0) return false;
        struct pollfd p = {k->tcp, POLLOUT, 0};
        poll(&p, 1, (int)left);
    }
    return true;
}

/* -- UDP output -------------------------------------------------------------------------- */

static size_t dgram_body_at(const rlb_conn *k) { return UDP_HDR + (k->sealed ? 8u : 0u); }

static size_t dgram_body_cap(const rlb_conn *k) {
    return DGRAM_MAX - UDP_HDR - (k->sealed ? SEAL_DGRAM : 0u);
}

/* Sends the body already written at dgram_body_at(k) in dg_tx. */
static void dgram_send(rlb_conn *k, size_t body_len) {
    uint8_t *d = k->dg_tx;
    d[0] = 'R', d[1] = 'B', d[2] = RLB_PROTOCOL_VERSION;
    d[3] = F_BUNDLES | (k->sealed ? F_SEALED : 0);
    for (int i = 0; i < 8; i++) d[4 + i] = (uint8_t)(k->token >> (56 - 8 * i));
    size_t len = UDP_HDR + body_len;
    if (k->sealed) {
        uint64_t ctr = ++k->dgram_tx;
        for (int i = 0; i < 8; i++) d[12 + i] = (uint8_t)(ctr >> (56 - 8 * i));
        rlb_seal(k->keys.kc2s, ctr, d, 20, d + 20, body_len, d + 20 + body_len);
        len = 20 + body_len + 16;
    }
    (void)send(k->udp, d, len, MSG_DONTWAIT); /* UDP: a full socket buffer is a lost datagram */
}

/* -- packets we send ----------------------------------------------------------------------- */

static void enc_heartbeat(rlb_conn *k, wbuf *w, int64_t now) {
    int64_t echo = k->peer_sent ? k->peer_sent + (now - k->peer_rx) : 0;
    wb_array(w, 6);
    wb_u64(w, T_HEARTBEAT);
    wb_i64(w, now);
    wb_i64(w, echo);
    wb_i64(w, rlb_wall_ns());
    wb_i64(w, k->peer_wall);
    wb_i64(w, k->peer_wall_rx);
}

static bool send_frame_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    frame_begin(k, &w);
    enc_heartbeat(k, &w, now);
    return frame_end(k, &w);
}

static void send_udp_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    wb_init(&w, k->dg_tx + dgram_body_at(k), dgram_body_cap(k));
    enc_heartbeat(k, &w, now);
    if (!w.overflow) dgram_send(k, w.len);
}

/* The value part of k values of a publish channel: Value for one, Batch for more. */
static void enc_part(wbuf *w, rlb_channel *ch, size_t n) {
    if (n == 1) {
        rlb_slot *s = ring_peek(&ch->ring, 0);
        wb_array(w, 5);
        wb_u64(w, T_VALUE);
        wb_u64(w, ch->id);
        wb_u64(w, ch->next_seq);
        wb_i64(w, s->stamp);
        wb_raw(w, s->data, s->len);
        return;
    }
    wb_array(w, 5);
    wb_u64(w, T_BATCH);
    wb_u64(w, ch->id);
    wb_u64(w, ch->next_seq);
    wb_array(w, (uint32_t)n);
    for (size_t i = 0; i < n; i++) wb_i64(w, ring_peek(&ch->ring, i)->stamp);
    wb_array(w, (uint32_t)n);
    for (size_t i = 0; i < n; i++) {
        rlb_slot *s = ring_peek(&ch->ring, i);
        wb_raw(w, s->data, s->len);
    }
}

static void sent(rlb_channel *ch, size_t n) {
    ring_release(&ch->ring, n);
    ch->next_seq += n;
    atomic_fetch_add_explicit(&ch->n_values, n, memory_order_relaxed);
}

/* An upper bound of a part's encoded size: header fields, then stamp + value each. */
#define PART_FIXED 24u

typedef struct plan {
    rlb_channel *ch;
    size_t n;
} plan;

static void send_plan(rlb_conn *k, plan *p, size_t np) {
    wbuf w;
    wb_init(&w, k->dg_tx + dgram_body_at(k), dgram_body_cap(k));
    if (np > 1) { /* one datagram for the round of every channel (protocol.md 6.16) */
        wb_array(&w, 2);
        wb_u64(&w, T_BUNDLE);
        wb_array(&w, (uint32_t)np);
    }
    for (size_t i = 0; i < np; i++) enc_part(&w, p[i].ch, p[i].n);
    if (w.overflow) return; /* cannot happen: the plan was sized to fit */
    dgram_send(k, w.len);
    for (size_t i = 0; i < np; i++) sent(p[i].ch, p[i].n);
}

static bool ready_to_send(const rlb_channel *ch) {
    return ch->dir == DIR_PUBLISH && ch->bind == BIND_ACKED;
}

static void send_udp_round(rlb_client *c) {
    rlb_conn *k = c->conn;
    plan p[64];
    size_t np = 0, used = 0, budget = dgram_body_cap(k) - 5; /* - the bundle's header */
    int dgrams = 0;
    uint32_t n = c->n_channels;
    for (uint32_t j = 0; j < n && dgrams < ROUND_DGRAMS; j++) {
        rlb_channel *ch = c->channels[(k->rr + j) % n];
        if (!ready_to_send(ch) || ch->transport != RLB_UDP) continue;
        for (;;) {
            size_t avail = ring_count(&ch->ring), take = 0, size = PART_FIXED;
            while (take < avail && take < 65535) {
                size_t more = 9 + ring_peek(&ch->ring, take)->len;
                if (used + size + more > budget) break;
                size += more;
                take++;
            }
            if (take > 0) {
                p[np].ch = ch;
                p[np++].n = take;
                used += size;
            }
            if (take == avail && np < 64) break;
            if (np == 0) { /* a single value larger than a datagram: dropped, counted */
                ring_release(&ch->ring, 1);
                atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
                continue;
            }
            send_plan(k, p, np);
            np = used = 0;
            if (++dgrams >= ROUND_DGRAMS || ring_count(&ch->ring) == 0) break;
        }
    }
    if (np > 0) send_plan(k, p, np);
    k->rr = n ? (k->rr + 1) % n : 0;
}

static void send_tcp_round(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (uint32_t j = 0; j < c->n_channels; j++) {
        rlb_channel *ch = c->channels[j];
        if (!ready_to_send(ch) || ch->transport != RLB_TCP) continue;
        for (;;) {
            size_t avail = ring_count(&ch->ring);
            if (ch->flow && ch->credit != UINT64_MAX) { /* credit (protocol.md 10.5) */
                uint64_t room = ch->credit > ch->next_seq ? ch->credit - ch->next_seq : 0;
                if (room < avail) avail = (size_t)room;
            }
            size_t take = avail < TCP_BATCH ? avail : TCP_BATCH;
            if (take == 0) break;
            wbuf w;
            for (;;) {
                frame_begin(k, &w);
                enc_part(&w, ch, take);
                if (frame_end(k, &w) || take == 1) break;
                take /= 2;
            }
            if (w.overflow) {
                if (k->out_len > 0) break; /* the buffer drains first */
                ring_release(&ch->ring, 1); /* larger than the whole buffer */
                atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
                continue;
            }
            sent(ch, take);
        }
    }
}

/* Credit for flow-controlled subscribe channels: what the ring has room for. */
static void send_credits(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (uint32_t j = 0; j < c->n_channels; j++) {
        rlb_channel *ch = c->channels[j];
        if (ch->dir != DIR_SUBSCRIBE || !ch->flow || ch->bind != BIND_ACKED) continue;
        uint64_t consumed = atomic_load_explicit(&ch->n_consumed, memory_order_relaxed);
        uint64_t limit = consumed - ch->credit_base;
        uint64_t step = ch->ring.cap / 4 ? ch->ring.cap / 4 : 1;
        if (limit < ch->credit_sent + step) continue;
        wbuf w;
        frame_begin(k, &w);
        wb_array(&w, 3);
        wb_u64(&w, T_CREDIT);
        wb_u64(&w, ch->id);
        wb_u64(&w, limit);
        if (frame_end(k, &w)) ch->credit_sent = limit;
    }
}

static bool send_topic_connect(rlb_conn *k, rlb_channel *ch) {
    wbuf w;
    frame_begin(k, &w);
    bool pub = ch->dir == DIR_PUBLISH;
    uint64_t buffer = 1;
    if (!pub && ch->mode == RLB_QUEUE) { /* first credit: the ring's free room */
        uint64_t consumed = atomic_load_explicit(&ch->n_consumed, memory_order_relaxed);
        uint64_t occupied = ch->pushed - consumed;
        buffer = ch->ring.cap > occupied ? ch->ring.cap - occupied : 1;
        ch->credit_base = consumed - buffer; /* limit = consumed - base (mod 2^64) */
        ch->credit_sent = buffer;
    }
    wb_array(&w, 16);
    wb_u64(&w, T_TOPIC);
    wb_u64(&w, ch->id);
    wb_str(&w, pub ? "publish" : "subscribe", pub ? 7 : 9);
    wb_str(&w, ch->topic, strlen(ch->topic));
    wb_str(&w, ch->msg_type, strlen(ch->msg_type));
    if (ch->field) wb_str(&w, ch->field, strlen(ch->field));
    else wb_nil(&w);
    wb_str(&w, ch->transport == RLB_TCP ? "tcp" : "udp", 3);
    wb_u64(&w, buffer);
    wb_nil(&w);            /* reliability: by transport */
    wb_u64(&w, ch->qos_depth);
    wb_u64(&w, 0);         /* max_age_ms */
    wb_u64(&w, 0);         /* redundancy */
    wb_bool(&w, false);    /* latest */
    wb_bool(&w, ch->flow);
    wb_bool(&w, pub);      /* loss_report: the server's first-hop counts, publish only */
    wb_str(&w, "volatile", 8);
    return frame_end(k, &w);
}

/* -- packets we receive -------------------------------------------------------------------- */

static void malformed(rlb_conn *k) { k->malformed++; }

static void deliver(rlb_channel *ch, uint64_t seq, int64_t stamp, const uint8_t *v, size_t len) {
    if (ch->has_highest && seq <= ch->highest) {
        atomic_fetch_add_explicit(&ch->n_duplicates, 1, memory_order_relaxed);
        return;
    }
    if (ch->has_highest && seq > ch->highest + 1)
        atomic_fetch_add_explicit(&ch->n_lost, seq - ch->highest - 1, memory_order_relaxed);
    ch->has_highest = true;
    ch->highest = seq;
    chan_deliver(ch, stamp, v, len);
}

/* A Value or Batch body (tag already read). */
static bool values(rlb_client *c, mp_cur *m, uint64_t tag) {
    uint64_t id, seq;
    if (!mp_u64(m, &id) || !mp_u64(m, &seq)) return false;
    rlb_channel *ch = channel_of(c, id);
    bool ours = ch != NULL && ch->dir == DIR_SUBSCRIBE && ch->bind == BIND_ACKED;
    if (tag == T_VALUE) {
        int64_t stamp;
        if (!mp_i64(m, &stamp)) return false;
        const uint8_t *v = m->p;
        if (!mp_skip(m)) return false;
        if (ours) deliver(ch, seq, stamp, v, (size_t)(m->p - v));
        return true;
    }
    uint32_t ns, nv;
    if (!mp_array(m, &ns)) return false;
    mp_cur stamps = *m;
    for (uint32_t i = 0; i < ns; i++) {
        int64_t st;
        if (!mp_i64(m, &st)) return false;
    }
    if (!mp_array(m, &nv) || nv != ns) return false;
    for (uint32_t i = 0; i < nv; i++) {
        int64_t stamp;
        mp_i64(&stamps, &stamp);
        const uint8_t *v = m->p;
        if (!mp_skip(m)) return false;
        if (ours) deliver(ch, seq + i, stamp, v, (size_t)(m->p - v));
    }
    return true;
}

static void session_lost(rlb_client *c, const char *why);

static void on_error(rlb_client *c, mp_cur *m, bool topic) {
    uint64_t code = 0, id = 0;
    const char *reason = "";
    uint32_t rlen = 0;
    char text[256];
    if (topic) { /* TopicError [6, channel, code, reason] */
        if (!mp_u64(m, &id) || !mp_u64(m, &code)) return malformed(c->conn);
        mp_str(m, &reason, &rlen);
    } else {     /* Error [12, code, reason, channel|nil, values] */
        if (!mp_u64(m, &code)) return malformed(c->conn);
        if (mp_str(m, &reason, &rlen) && !mp_nil(m)) mp_u64(m, &id);
    }
    snprintf(text, sizeof text, "%.*s", (int)(rlen < 255 ? rlen : 255), reason);
    rlb_channel *ch = channel_of(c, id);
    if (ch != NULL) {
        atomic_fetch_add_explicit(&ch->n_errors, 1, memory_order_relaxed);
        atomic_store_explicit(&ch->last_error, (int)code, memory_order_relaxed);
        if (topic) ch->bind = BIND_REFUSED;
    }
    rlb_emit(c, topic ? RLB_EV_TOPIC_ERROR : RLB_EV_ERROR, (int)code, (uint32_t)id, text);
}

static void on_packet(rlb_client *c, const uint8_t *body, size_t len, bool in_bundle);

static void dispatch(rlb_client *c, mp_cur *m, uint64_t tag, bool in_bundle) {
    rlb_conn *k = c->conn;
    int64_t now = rlb_mono_ns();
    if (in_bundle && tag != T_VALUE && tag != T_BATCH) return malformed(k);
    switch (tag) {
    case T_VALUE:
    case T_BATCH:
        if (!values(c, m, tag)) malformed(k);
        break;
    case T_TOPICACK: {
        uint64_t id, credit = UINT64_MAX;
        const char *type;
        uint32_t tl;
        if (!mp_u64(m, &id) || !mp_str(m, &type, &tl)) return malformed(k);
        if (mp_skip(m) && mp_skip(m) && !mp_nil(m)) mp_u64(m, &credit); /* initial, schema */
        rlb_channel *ch = channel_of(c, id);
        if (ch == NULL || ch->bind != BIND_SENT) break;
        ch->bind = BIND_ACKED;
        ch->credit = ch->dir == DIR_PUBLISH && ch->flow ? credit : UINT64_MAX;
        atomic_store(&ch->bound, true);
        break;
    }
    case T_TOPICERR: on_error(c, m, true); break;
    case T_ERROR: on_error(c, m, false); break;
    case T_HEARTBEAT: {
        int64_t sent_ns = 0, echo = 0, wall = 0;
        if (!mp_i64(m, &sent_ns)) return malformed(k);
        uint32_t left = 0;
        (void)left;
        if (mp_i64(m, &echo) && mp_i64(m, &wall)) {
            k->peer_wall = wall;
            k->peer_wall_rx = rlb_wall_ns();
        }
        k->peer_sent = sent_ns;
        k->peer_rx = now;
        break;
    }
    case T_DISCONNECT: {
        uint64_t code = 0;
        const char *reason = "";
        uint32_t rl = 0;
        char text[256];
        if (mp_u64(m, &code)) mp_str(m, &reason, &rl);
        snprintf(text, sizeof text, "%.*s", (int)(rl < 255 ? rl : 255), reason);
        rlb_emit(c, RLB_EV_DISCONNECT, (int)code, 0, text);
        session_lost(c, text);
        return;
    }
    case T_BUNDLE: {
        uint32_t n;
        if (!mp_array(m, &n)) return malformed(k);
        for (uint32_t i = 0; i < n; i++) {
            const uint8_t *part = m->p;
            if (!mp_skip(m)) return malformed(k);
            on_packet(c, part, (size_t)(m->p - part), true);
        }
        break;
    }
    case T_CREDIT: {
        uint64_t id, limit;
        if (!mp_u64(m, &id) || !mp_u64(m, &limit)) return malformed(k);
        rlb_channel *ch = channel_of(c, id);
        if (ch && ch->dir == DIR_PUBLISH && ch->flow && (ch->credit == UINT64_MAX || limit > ch->credit))
            ch->credit = limit;
        break;
    }
    case T_LOSS: {
        uint32_t n, f;
        if (!mp_array(m, &n)) return malformed(k);
        for (uint32_t i = 0; i < n; i++) {
            uint64_t id, received, lost;
            if (!mp_array(m, &f) || f < 4 || !mp_u64(m, &id) || !mp_u64(m, &received) ||
                !mp_u64(m, &lost))
                return malformed(k);
            for (uint32_t j = 3; j < f; j++)
                if (!mp_skip(m)) return malformed(k);
            rlb_channel *ch = channel_of(c, id);
            if (ch && ch->dir == DIR_PUBLISH) {
                atomic_store_explicit(&ch->n_srv_received, received, memory_order_relaxed);
                atomic_store_explicit(&ch->n_lost, lost, memory_order_relaxed);
            }
        }
        break;
    }
    default: /* Stats, RosLoss, service packets, a late ConnectAck: nothing to do */
        break;
    }
}

static void on_packet(rlb_client *c, const uint8_t *body, size_t len, bool in_bundle) {
    mp_cur m;
    uint32_t n;
    uint64_t tag;
    mp_init(&m, body, len);
    if (!mp_array(&m, &n) || n < 1 || !mp_u64(&m, &tag)) return malformed(c->conn);
    if (!in_bundle) c->conn->last_rx = rlb_mono_ns();
    dispatch(c, &m, tag, in_bundle);
}

/* -- TCP input ----------------------------------------------------------------------------- */

/* Opens complete sealed records from rec into in; false: the stream cannot be trusted. */
static bool open_records(rlb_conn *k) {
    size_t at = 0;
    while (k->rec_len - at >= 8) {
        const uint8_t *h = k->rec + at;
        uint32_t len = (uint32_t)h[4] << 24 | (uint32_t)h[5] << 16 | (uint32_t)h[6] << 8 | h[7];
        if (h[0] != 'R' || h[1] != 'B' || h[2] != RLB_PROTOCOL_VERSION || !(h[3] & F_SEALED) ||
            len < 16 || len > RECORD_MAX + 16)
            return false;
        if (k->rec_len - at < 8 + (size_t)len) break;
        size_t m = len - 16;
        if (k->in_off > 0) {
            memmove(k->in, k->in + k->in_off, k->in_len - k->in_off);
            k->in_len -= k->in_off;
            k->in_off = 0;
        }
        if (k->cap - k->in_len < m) break; /* the frames are read first */
        uint8_t hdr[8];
        memcpy(hdr, h, 8);
        if (!rlb_open(k->keys.rs2c, k->rec_rx, hdr, 8, k->rec + at + 8, m, k->rec + at + 8 + m))
            return false;
        k->rec_rx++;
        memcpy(k->in + k->in_len, k->rec + at + 8, m);
        k->in_len += m;
        at += 8 + len;
    }
    memmove(k->rec, k->rec + at, k->rec_len - at);
    k->rec_len -= at;
    return true;
}

/* Reads what the socket has; false on EOF or error. */
static bool tcp_read(rlb_conn *k) {
    for (int i = 0; i < 8; i++) {
        ssize_t n;
        if (k->sealed) {
            size_t room = RECORD_MAX + 24 + 8 - k->rec_len;
            if (room == 0) return open_records(k);
            n = recv(k->tcp, k->rec + k->rec_len, room, MSG_DONTWAIT);
            if (n > 0) {
                k->rec_len += (size_t)n;
                if (!open_records(k)) return false;
            }
        } else {
            if (k->in_off > 0) {
                memmove(k->in, k->in + k->in_off, k->in_len - k->in_off);
                k->in_len -= k->in_off;
                k->in_off = 0;
            }
            if (k->in_len == k->cap) return true;
            n = recv(k->tcp, k->in + k->in_len, k->cap - k->in_len, MSG_DONTWAIT);
            if (n > 0) k->in_len += (size_t)n;
        }
        if (n == 0) return false;
        if (n < 0) return errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR;
    }
    return true;
}

/* The next complete frame's body in in, or NULL; consumed by the caller via in_off. A frame
 * larger than the buffer is skipped (counted malformed); -1 in *bad: the framing is lost. */
static const uint8_t *next_frame(rlb_conn *k, size_t *len, bool *bad) {
    *bad = false;
    while (k->skip > 0 && k->in_off < k->in_len) {
        size_t n = k->in_len - k->in_off < k->skip ? k->in_len - k->in_off : k->skip;
        k->in_off += n;
        k->skip -= n;
    }
    if (k->in_len - k->in_off < 8) return NULL;
    const uint8_t *h = k->in + k->in_off;
    if (h[0] != 'R' || h[1] != 'B' || h[2] != RLB_PROTOCOL_VERSION || (h[3] & F_SEALED)) {
        *bad = true;
        return NULL;
    }
    size_t n = (size_t)h[4] << 24 | (size_t)h[5] << 16 | (size_t)h[6] << 8 | h[7];
    if (n > k->cap - 8) {
        k->in_off += 8;
        k->skip = n;
        malformed(k);
        return next_frame(k, len, bad);
    }
    if (k->in_len - k->in_off < 8 + n) return NULL;
    k->in_off += 8 + n;
    *len = n;
    return h + 8;
}

/* -- UDP input ----------------------------------------------------------------------------- */

static bool replay_ok(rlb_conn *k, uint64_t ctr) {
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
static void udp_datagram(rlb_client *c, uint8_t *d, size_t n) {
    rlb_conn *k = c->conn;
    if (n < UDP_HDR || d[0] != 'R' || d[1] != 'B' || d[2] != RLB_PROTOCOL_VERSION) {
        malformed(k);
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
        if (!replay_ok(k, ctr)) return;
        body = d + 20;
    }
    on_packet(c, body, len, false);
}

static void udp_read(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (int i = 0; i < 256 && k->udp >= 0 && k->up; i++) {
        ssize_t n = recv(k->udp, k->dg_rx, RX_DGRAM, MSG_DONTWAIT);
        if (n < 0) return;
        udp_datagram(c, k->dg_rx, (size_t)n);
    }
}

/* -- test and fuzz entry points: bytes as if received, no socket -------------------------- */

void rlb_debug_bind_all(rlb_client *c, uint64_t token) {
    c->conn->token = token;
    for (uint32_t i = 0; i < c->n_channels; i++) c->channels[i]->bind = BIND_ACKED;
}

void rlb_debug_feed_datagram(rlb_client *c, const uint8_t *d, size_t n) {
    if (n > RX_DGRAM) return;
    memcpy(c->conn->dg_rx, d, n);
    udp_datagram(c, c->conn->dg_rx, n);
}

void rlb_debug_feed_stream(rlb_client *c, const uint8_t *bytes, size_t n) {
    rlb_conn *k = c->conn;
    while (n > 0) {
        if (k->in_off > 0) {
            memmove(k->in, k->in + k->in_off, k->in_len - k->in_off);
            k->in_len -= k->in_off;
            k->in_off = 0;
        }
        size_t room = k->cap - k->in_len, take = n < room ? n : room;
        memcpy(k->in + k->in_len, bytes, take);
        k->in_len += take;
        bytes += take;
        n -= take;
        for (;;) {
            size_t len;
            bool bad;
            const uint8_t *f = next_frame(k, &len, &bad);
            if (bad) { /* the framing is lost: a real connection would end here */
                k->in_off = k->in_len = k->skip = 0;
                break;
            }
            if (f == NULL) break;
            on_packet(c, f, len, false);
        }
    }
}

uint64_t rlb_debug_malformed(const rlb_client *c) { return c->conn->malformed; }

/* -- opening a session ------------------------------------------------------------------- */

static int set_nonblock(int fd) { return fcntl(fd, F_SETFL, fcntl(fd, F_GETFL, 0) | O_NONBLOCK); }

static rlb_status open_sockets(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    char port[8];
    snprintf(port, sizeof port, "%u", (unsigned)c->cfg.port);
    struct addrinfo hints, *res = NULL;
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    if (getaddrinfo(c->cfg.host, port, &hints, &res) != 0 || res == NULL) return RLB_E_CONNECT;
    rlb_status rc = RLB_E_CONNECT;
    for (struct addrinfo *a = res; a != NULL && rc != RLB_OK; a = a->ai_next) {
        k->tcp = socket(a->ai_family, SOCK_STREAM | SOCK_CLOEXEC, 0);
        k->udp = socket(a->ai_family, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        if (k->tcp < 0 || k->udp < 0 || set_nonblock(k->tcp) < 0 || set_nonblock(k->udp) < 0 ||
            connect(k->udp, a->ai_addr, a->ai_addrlen) < 0) {
            close_sockets(k);
            continue;
        }
        if (connect(k->tcp, a->ai_addr, a->ai_addrlen) < 0 && errno != EINPROGRESS) {
            close_sockets(k);
            continue;
        }
        struct pollfd p = {k->tcp, POLLOUT, 0};
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        int err = 0;
        socklen_t el = sizeof err;
        if (left <= 0 || poll(&p, 1, (int)left) != 1 ||
            getsockopt(k->tcp, SOL_SOCKET, SO_ERROR, &err, &el) < 0 || err != 0) {
            close_sockets(k);
            continue;
        }
        int one = 1; /* values go out when written, not when Nagle lets them (docs) */
        setsockopt(k->tcp, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        rc = RLB_OK;
    }
    freeaddrinfo(res);
    return rc;
}

/* Waits for the next TCP frame of the handshake; NULL on timeout or a broken connection. */
static const uint8_t *handshake_frame(rlb_conn *k, int64_t deadline, size_t *len) {
    for (;;) {
        bool bad;
        const uint8_t *f = next_frame(k, len, &bad);
        if (f != NULL) return f;
        if (bad) return NULL;
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if (left <= 0) return NULL;
        struct pollfd p = {k->tcp, POLLIN, 0};
        if (poll(&p, 1, (int)left) < 0 && errno != EINTR) return NULL;
        if (!tcp_read(k) && k->in_len - k->in_off < 8) return NULL;
    }
}

static rlb_status handshake(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    uint8_t nc[16], t[300], proof[32];
    size_t tlen = 0;
    bool keyed = c->psk_len > 0;
    if (keyed) randombytes_buf(nc, sizeof nc);
    wbuf w;
    frame_begin(k, &w);
    wb_array(&w, 4);
    wb_u64(&w, T_HELLO);
    wb_u64(&w, RLB_PROTOCOL_VERSION);
    wb_str(&w, c->name, strlen(c->name));
    wb_bin(&w, nc, keyed ? 16 : 0);
    frame_end(k, &w);
    if (!tcp_flush_blocking(k, deadline)) return RLB_E_CONNECT;
    for (;;) {
        size_t len;
        const uint8_t *f = handshake_frame(k, deadline, &len);
        if (f == NULL) return RLB_E_CONNECT;
        mp_cur m;
        uint32_t n;
        uint64_t tag;
        mp_init(&m, f, len);
        if (!mp_array(&m, &n) || !mp_u64(&m, &tag)) return RLB_E_CONNECT;
        if (tag == T_CONNERR) {
            uint64_t code = 0;
            const char *reason = "";
            uint32_t rl = 0;
            char text[256];
            if (mp_u64(&m, &code)) mp_str(&m, &reason, &rl);
            snprintf(text, sizeof text, "%.*s", (int)(rl < 255 ? rl : 255), reason);
            rlb_emit(c, RLB_EV_DISCONNECT, (int)code, 0, text);
            return code == 21 ? RLB_E_AUTH : RLB_E_REFUSED;
        }
        if (tag == T_CHALLENGE) {
            const uint8_t *ns, *ps;
            uint32_t nl, pl;
            if (!keyed || !mp_bin(&m, &ns, &nl) || nl != 16 || !mp_bin(&m, &ps, &pl) || pl != 32)
                return RLB_E_AUTH;
            tlen = rlb_transcript(c->name, nc, ns, t, sizeof t);
            rlb_proof(c->psk, c->psk_len, "server-proof", t, tlen, proof);
            if (sodium_memcmp(proof, ps, 32) != 0) { /* a server without our key */
                frame_begin(k, &w);
                wb_array(&w, 3);
                wb_u64(&w, T_DISCONNECT);
                wb_u64(&w, 21);
                wb_str(&w, "server proof wrong", 18);
                frame_end(k, &w);
                tcp_flush_blocking(k, deadline);
                return RLB_E_AUTH;
            }
            rlb_derive(c->psk, c->psk_len, nc, ns, t, tlen, &k->keys);
            rlb_proof(c->psk, c->psk_len, "client-proof", t, tlen, proof);
            frame_begin(k, &w);
            wb_array(&w, 2);
            wb_u64(&w, T_PROOF);
            wb_bin(&w, proof, 32);
            frame_end(k, &w);
            if (!tcp_flush_blocking(k, deadline)) return RLB_E_CONNECT;
            /* From the ConnectAck on the server sends records: what follows is one. */
            size_t rest = k->in_len - k->in_off;
            if (rest > RECORD_MAX + 32) return RLB_E_CONNECT;
            memcpy(k->rec, k->in + k->in_off, rest);
            k->rec_len = rest;
            k->in_off = k->in_len = 0;
            k->sealed = true;
            if (!open_records(k)) return RLB_E_AUTH;
            continue;
        }
        if (tag == T_ACK) {
            uint64_t session, token, hb, to;
            uint32_t nl;
            if (keyed && !k->sealed) return RLB_E_AUTH; /* no downgrade (16.1) */
            if (!mp_u64(&m, &session) || !mp_u64(&m, &token) || !mp_u64(&m, &hb) ||
                !mp_u64(&m, &to) || !mp_array(&m, &nl) || token == 0 || hb == 0)
                return RLB_E_CONNECT;
            k->token = token;
            k->hb_ms = (uint32_t)hb;
            k->timeout_ms = (uint32_t)to;
            return RLB_OK;
        }
        /* anything else before the ack is ignored */
    }
}

static void reset_bindings(rlb_client *c) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        rlb_channel *ch = c->channels[i];
        ch->bind = BIND_NONE;
        ch->next_seq = 0; /* every binding numbers from 0 (protocol.md 10.5) */
        ch->credit = UINT64_MAX;
        ch->has_highest = false;
        atomic_store(&ch->bound, false);
    }
}

static bool spin_io(rlb_client *c, int timeout_ms);

rlb_status conn_open(rlb_client *c) {
    rlb_conn *k = c->conn;
    int64_t start = rlb_mono_ns();
    int64_t deadline = start + (int64_t)c->cfg.connect_timeout_ms * 1000000;
    close_sockets(k);
    k->out_len = k->wire_off = k->wire_len = k->in_off = k->in_len = k->rec_len = k->skip = 0;
    k->dgram_tx = k->rec_tx = k->rec_rx = k->replay_top = 0;
    memset(k->replay_bits, 0, sizeof k->replay_bits);
    k->peer_sent = k->peer_wall = 0;
    reset_bindings(c);
    rlb_status rc = open_sockets(c, deadline);
    if (rc == RLB_OK) rc = handshake(c, deadline);
    if (rc != RLB_OK) {
        close_sockets(k);
        return rc;
    }
    k->up = true;
    k->last_rx = k->last_hb = rlb_mono_ns();
    send_udp_heartbeat(k, k->last_hb); /* registers our UDP address (protocol.md 8.3) */
    for (uint32_t i = 0; i < c->n_channels; i++) {
        if (!send_topic_connect(k, c->channels[i])) {
            close_sockets(k);
            return RLB_E_NOMEM; /* more bindings than the TCP buffer holds */
        }
        c->channels[i]->bind = BIND_SENT;
    }
    for (;;) {
        bool pending = false, refused = false;
        for (uint32_t i = 0; i < c->n_channels; i++) {
            pending |= c->channels[i]->bind == BIND_SENT;
            refused |= c->channels[i]->bind == BIND_REFUSED;
        }
        if (!pending) {
            if (refused && !c->connected_once) {
                close_sockets(k);
                return RLB_E_REFUSED;
            }
            break;
        }
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if (left <= 0 || !spin_io(c, (int)(left < 50 ? left : 50)) || !k->up) {
            close_sockets(k);
            return RLB_E_CONNECT;
        }
    }
    atomic_fetch_add(&c->sessions, 1);
    k->backoff_ms = c->cfg.backoff_initial_ms;
    rlb_set_link(c, RLB_LINK_CONNECTED);
    rlb_emit(c, RLB_EV_CONNECTED, 0, 0, NULL);
    return RLB_OK;
}

/* -- the session's life ------------------------------------------------------------------ */

static uint64_t next_random(rlb_client *c) { /* xorshift64: jitter of the backoff */
    c->rng ^= c->rng << 13;
    c->rng ^= c->rng >> 7;
    c->rng ^= c->rng << 17;
    return c->rng;
}

static void session_lost(rlb_client *c, const char *why) {
    rlb_conn *k = c->conn;
    (void)why;
    if (!k->up) return;
    close_sockets(k);
    reset_bindings(c);
    rlb_set_link(c, RLB_LINK_LOST);
    if (!c->cfg.reconnect) {
        k->closed = true;
        return;
    }
    uint32_t b = k->backoff_ms ? k->backoff_ms : 1;
    k->retry_at = rlb_mono_ns() + (int64_t)(b - b / 5 + next_random(c) % (b / 5 * 2 + 1)) * 1000000;
}

/* Receives (waiting up to timeout_ms) and dispatches; false when the session broke. */
static bool spin_io(rlb_client *c, int timeout_ms) {
    rlb_conn *k = c->conn;
    if (!tcp_flush(k)) {
        session_lost(c, "send failed");
        return false;
    }
    struct pollfd p[2] = {{k->tcp, POLLIN, 0}, {k->udp, POLLIN, 0}};
    if (k->wire_off < k->wire_len) p[0].events |= POLLOUT;
    int r = poll(p, 2, timeout_ms);
    if (r < 0 && errno != EINTR) return true;
    if (p[0].revents & (POLLIN | POLLHUP | POLLERR)) {
        bool ok = tcp_read(k);
        for (;;) {
            size_t len;
            bool bad;
            const uint8_t *f = next_frame(k, &len, &bad);
            if (bad) ok = false;
            if (f == NULL || !k->up) break;
            on_packet(c, f, len, false);
        }
        if (!ok && k->up) {
            session_lost(c, "connection closed");
            return false;
        }
    }
    if (k->up && (p[1].revents & POLLIN)) udp_read(c);
    return k->up;
}

rlb_status conn_spin(rlb_client *c, uint32_t timeout_ms) {
    rlb_conn *k = c->conn;
    if (k->closed) return RLB_E_CLOSED;
    int64_t now = rlb_mono_ns();
    if (!k->up) {
        if (now < k->retry_at) {
            int64_t wait = (k->retry_at - now) / 1000000;
            if (wait > (int64_t)timeout_ms) wait = timeout_ms;
            struct timespec ts = {wait / 1000, (long)(wait % 1000) * 1000000};
            nanosleep(&ts, NULL);
            return RLB_OK;
        }
        rlb_set_link(c, RLB_LINK_CONNECTING);
        if (conn_open(c) != RLB_OK) {
            rlb_set_link(c, RLB_LINK_LOST);
            uint32_t b = k->backoff_ms * 2;
            k->backoff_ms = b > c->cfg.backoff_max_ms ? c->cfg.backoff_max_ms : b;
            b = k->backoff_ms;
            k->retry_at = rlb_mono_ns() + (int64_t)(b - b / 5 + next_random(c) % (b / 5 * 2 + 1)) * 1000000;
        }
        return RLB_OK;
    }
    int64_t next_hb = k->last_hb + (int64_t)k->hb_ms * 1000000;
    int64_t until = (next_hb - now) / 1000000;
    if (until < 0) until = 0;
    int wait = (int)(until < (int64_t)timeout_ms ? until : (int64_t)timeout_ms);
    if (!spin_io(c, wait)) return RLB_OK;
    send_udp_round(c);
    send_tcp_round(c);
    send_credits(c);
    now = rlb_mono_ns();
    if (now >= next_hb) {
        k->last_hb = now;
        send_frame_heartbeat(k, now);
        send_udp_heartbeat(k, now);
    }
    int64_t silence = now - k->last_rx;
    if (silence >= (int64_t)k->timeout_ms * 1000000) {
        session_lost(c, "watchdog: the server is silent");
        return RLB_OK;
    }
    rlb_set_link(c, silence * 2 < (int64_t)k->hb_ms * 3000000 ? RLB_LINK_CONNECTED
                                                               : RLB_LINK_DEGRADED);
    if (!tcp_flush(k)) session_lost(c, "send failed");
    return RLB_OK;
}

void conn_goodbye(rlb_client *c) {
    rlb_conn *k = c->conn;
    if (k == NULL || !k->up) return;
    /* A goodbye on UDP follows the session's value datagrams on their own path, so the
     * server has read them all before it closes the session; then the same on TCP. */
    wbuf w;
    wb_init(&w, k->dg_tx + dgram_body_at(k), dgram_body_cap(k));
    wb_array(&w, 3);
    wb_u64(&w, T_DISCONNECT);
    wb_u64(&w, 0);
    wb_str(&w, "bye", 3);
    bool any_udp = false;
    for (uint32_t i = 0; i < c->n_channels; i++)
        any_udp |= c->channels[i]->dir == DIR_PUBLISH && c->channels[i]->transport == RLB_UDP;
    if (any_udp) {
        dgram_send(k, w.len);
        int64_t end = rlb_mono_ns() + 500000000; /* the server closes TCP once it read it */
        for (;;) {
            int64_t left = (end - rlb_mono_ns()) / 1000000;
            struct pollfd p = {k->tcp, POLLIN, 0};
            if (left <= 0 || poll(&p, 1, (int)left) <= 0) break;
            ssize_t n = recv(k->tcp, k->rec, RECORD_MAX, MSG_DONTWAIT);
            if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) break;
        }
    } else {
        frame_begin(k, &w);
        wb_array(&w, 3);
        wb_u64(&w, T_DISCONNECT);
        wb_u64(&w, 0);
        wb_str(&w, "bye", 3);
        frame_end(k, &w);
        tcp_flush_blocking(k, rlb_mono_ns() + 500000000);
    }
    shutdown(k->tcp, SHUT_WR);
    close_sockets(k);
}
