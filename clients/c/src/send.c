/* What the client sends: heartbeats, bindings, credit, and the rounds of values taken from the
 * rings (one bundle datagram for all UDP channels, a Batch frame per TCP channel). */
#include <string.h>

#include "conn.h"

/* -- packets we send ----------------------------------------------------------------------- */

static void enc_heartbeat(rlb_conn *k, wbuf *w, int64_t now) {
    int64_t echo = k->peer_sent ? k->peer_sent + (now - k->peer_rx) : 0;
    rlbi_wb_array(w, 6);
    rlbi_wb_u64(w, T_HEARTBEAT);
    rlbi_wb_i64(w, now);
    rlbi_wb_i64(w, echo);
    rlbi_wb_i64(w, rlb_wall_ns());
    rlbi_wb_i64(w, k->peer_wall);
    rlbi_wb_i64(w, k->peer_wall_rx);
}

bool rlbi_send_tcp_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    rlbi_tcp_frame_begin(k, &w);
    enc_heartbeat(k, &w, now);
    return rlbi_tcp_frame_end(k, &w);
}

void rlbi_send_udp_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    rlbi_wb_init(&w, k->dg_tx + rlbi_udp_body_at(k), rlbi_udp_body_cap(k));
    enc_heartbeat(k, &w, now);
    if (!w.overflow) rlbi_udp_send(k, w.len);
}

/* The value part of k values of a publish channel: Value for one, Batch for more. */
static rlb_slot *hist_slot(const rlb_channel *ch, uint32_t i) { /* i = 0: the oldest */
    size_t at = (ch->hist_at + i) % ch->redundancy;
    return (rlb_slot *)(void *)(ch->hist + ch->ring.stride * at);
}

/* Bytes the repeated values add to a part: a stamp and a value each. */
static size_t hist_bytes(const rlb_channel *ch) {
    size_t n = 0;
    for (uint32_t i = 0; i < ch->hist_n; i++) n += 9 + hist_slot(ch, i)->len;
    return n;
}

/* With redundancy, a Batch that starts with the previous values (protocol.md 10.3). */
static void enc_redundant(wbuf *w, rlb_channel *ch, size_t n) {
    uint32_t h = ch->hist_n;
    rlbi_wb_array(w, 5);
    rlbi_wb_u64(w, T_BATCH);
    rlbi_wb_u64(w, ch->id);
    rlbi_wb_u64(w, ch->next_seq - h);
    rlbi_wb_array(w, (uint32_t)(h + n));
    for (uint32_t i = 0; i < h; i++) rlbi_wb_i64(w, hist_slot(ch, i)->stamp);
    for (size_t i = 0; i < n; i++) rlbi_wb_i64(w, rlbi_ring_peek(&ch->ring, i)->stamp);
    rlbi_wb_array(w, (uint32_t)(h + n));
    for (uint32_t i = 0; i < h; i++) {
        rlb_slot *s = hist_slot(ch, i);
        rlbi_wb_raw(w, s->data, s->len);
    }
    for (size_t i = 0; i < n; i++) {
        rlb_slot *s = rlbi_ring_peek(&ch->ring, i);
        rlbi_wb_raw(w, s->data, s->len);
    }
}

static void enc_part(wbuf *w, rlb_channel *ch, size_t n) {
    if (ch->hist_n > 0) {
        enc_redundant(w, ch, n);
        return;
    }
    if (n == 1) {
        rlb_slot *s = rlbi_ring_peek(&ch->ring, 0);
        rlbi_wb_array(w, 5);
        rlbi_wb_u64(w, T_VALUE);
        rlbi_wb_u64(w, ch->id);
        rlbi_wb_u64(w, ch->next_seq);
        rlbi_wb_i64(w, s->stamp);
        rlbi_wb_raw(w, s->data, s->len);
        return;
    }
    rlbi_wb_array(w, 5);
    rlbi_wb_u64(w, T_BATCH);
    rlbi_wb_u64(w, ch->id);
    rlbi_wb_u64(w, ch->next_seq);
    rlbi_wb_array(w, (uint32_t)n);
    for (size_t i = 0; i < n; i++) rlbi_wb_i64(w, rlbi_ring_peek(&ch->ring, i)->stamp);
    rlbi_wb_array(w, (uint32_t)n);
    for (size_t i = 0; i < n; i++) {
        rlb_slot *s = rlbi_ring_peek(&ch->ring, i);
        rlbi_wb_raw(w, s->data, s->len);
    }
}

static void sent(rlb_channel *ch, size_t n) {
    for (size_t i = 0; ch->hist && i < n; i++) { /* keep the last `redundancy` values */
        rlb_slot *s = rlbi_ring_peek(&ch->ring, i);
        if (ch->hist_n == ch->redundancy) ch->hist_at = (ch->hist_at + 1) % ch->redundancy;
        else ch->hist_n++;
        memcpy(hist_slot(ch, ch->hist_n - 1), s, sizeof *s + s->len);
    }
    rlbi_ring_release(&ch->ring, n);
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
    rlbi_wb_init(&w, k->dg_tx + rlbi_udp_body_at(k), rlbi_udp_body_cap(k));
    if (np > 1) { /* one datagram for the round of every channel (protocol.md 6.16) */
        rlbi_wb_array(&w, 2);
        rlbi_wb_u64(&w, T_BUNDLE);
        rlbi_wb_array(&w, (uint32_t)np);
    }
    for (size_t i = 0; i < np; i++) enc_part(&w, p[i].ch, p[i].n);
    if (w.overflow) return; /* cannot happen: the plan was sized to fit */
    rlbi_udp_send(k, w.len);
    for (size_t i = 0; i < np; i++) sent(p[i].ch, p[i].n);
}

static bool ready_to_send(const rlb_channel *ch) {
    return ch->dir == DIR_PUBLISH && ch->bind == BIND_ACKED;
}

void rlbi_send_udp_round(rlb_client *c) {
    rlb_conn *k = c->conn;
    plan p[64];
    size_t np = 0, used = 0, budget = rlbi_udp_body_cap(k) - 5; /* - the bundle's header */
    int dgrams = 0;
    uint32_t n = c->n_channels;
    for (uint32_t j = 0; j < n && dgrams < ROUND_DGRAMS; j++) {
        rlb_channel *ch = c->channels[(k->rr + j) % n];
        if (!ready_to_send(ch) || ch->transport != RLB_UDP) continue;
        for (;;) {
            size_t avail = rlbi_ring_count(&ch->ring), take = 0;
            size_t size = PART_FIXED + hist_bytes(ch);
            while (take < avail && take < 65535) {
                size_t more = 9 + rlbi_ring_peek(&ch->ring, take)->len;
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
                rlbi_ring_release(&ch->ring, 1);
                atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
                continue;
            }
            send_plan(k, p, np);
            np = used = 0;
            if (++dgrams >= ROUND_DGRAMS || rlbi_ring_count(&ch->ring) == 0) break;
        }
    }
    if (np > 0) send_plan(k, p, np);
    k->rr = n ? (k->rr + 1) % n : 0;
}

void rlbi_send_tcp_round(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (uint32_t j = 0; j < c->n_channels; j++) {
        rlb_channel *ch = c->channels[j];
        if (!ready_to_send(ch) || ch->transport != RLB_TCP) continue;
        for (;;) {
            size_t avail = rlbi_ring_count(&ch->ring);
            if (ch->flow && ch->credit != UINT64_MAX) { /* credit (protocol.md 10.5) */
                uint64_t room = ch->credit > ch->next_seq ? ch->credit - ch->next_seq : 0;
                if (room < avail) avail = (size_t)room;
            }
            size_t take = avail < TCP_BATCH ? avail : TCP_BATCH;
            if (take == 0) break;
            wbuf w;
            for (;;) {
                rlbi_tcp_frame_begin(k, &w);
                enc_part(&w, ch, take);
                if (rlbi_tcp_frame_end(k, &w) || take == 1) break;
                take /= 2;
            }
            if (w.overflow) {
                if (k->out_len > 0) break; /* the buffer drains first */
                rlbi_ring_release(&ch->ring, 1); /* larger than the whole buffer */
                atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
                continue;
            }
            sent(ch, take);
            k->tcp_data = true;
        }
    }
}

/* Credit for flow-controlled subscribe channels: what the ring has room for. */
void rlbi_send_credits(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (uint32_t j = 0; j < c->n_channels; j++) {
        rlb_channel *ch = c->channels[j];
        if (ch->dir != DIR_SUBSCRIBE || !ch->flow || ch->bind != BIND_ACKED) continue;
        uint64_t consumed = atomic_load_explicit(&ch->n_consumed, memory_order_relaxed);
        uint64_t limit = consumed - ch->credit_base;
        uint64_t step = ch->ring.cap / 4 ? ch->ring.cap / 4 : 1;
        if (limit < ch->credit_sent + step) continue;
        wbuf w;
        rlbi_tcp_frame_begin(k, &w);
        rlbi_wb_array(&w, 3);
        rlbi_wb_u64(&w, T_CREDIT);
        rlbi_wb_u64(&w, ch->id);
        rlbi_wb_u64(&w, limit);
        if (rlbi_tcp_frame_end(k, &w)) ch->credit_sent = limit;
    }
}

/* A control packet: a TCP frame on a TCP session, a datagram on a UDP-only one. */
void rlbi_ctl_begin(rlb_conn *k, wbuf *w) {
    if (k->tcp >= 0) rlbi_tcp_frame_begin(k, w);
    else rlbi_wb_init(w, k->dg_tx + rlbi_udp_body_at(k), rlbi_udp_body_cap(k));
}

bool rlbi_ctl_end(rlb_conn *k, const wbuf *w) {
    if (k->tcp >= 0) return rlbi_tcp_frame_end(k, w);
    if (w->overflow) return false;
    rlbi_udp_send(k, w->len);
    return true;
}

bool rlbi_send_topic_connect(rlb_conn *k, rlb_channel *ch) {
    wbuf w;
    rlbi_ctl_begin(k, &w);
    bool pub = ch->dir == DIR_PUBLISH;
    uint64_t buffer = 1;
    if (!pub && ch->mode == RLB_QUEUE) { /* first credit: the ring's free room */
        uint64_t consumed = atomic_load_explicit(&ch->n_consumed, memory_order_relaxed);
        uint64_t occupied = ch->pushed - consumed;
        buffer = ch->ring.cap > occupied ? ch->ring.cap - occupied : 0; /* full: wait for a Credit */
        ch->credit_base = consumed - buffer; /* limit = consumed - base (mod 2^64) */
        ch->credit_sent = buffer;
    }
    rlbi_wb_array(&w, 16);
    rlbi_wb_u64(&w, T_TOPIC);
    rlbi_wb_u64(&w, ch->id);
    rlbi_wb_str(&w, pub ? "publish" : "subscribe", pub ? 7 : 9);
    rlbi_wb_str(&w, ch->topic, strlen(ch->topic));
    rlbi_wb_str(&w, ch->msg_type, strlen(ch->msg_type));
    if (ch->field) rlbi_wb_str(&w, ch->field, strlen(ch->field));
    else rlbi_wb_nil(&w);
    rlbi_wb_str(&w, ch->transport == RLB_TCP ? "tcp" : "udp", 3);
    rlbi_wb_u64(&w, buffer);
    rlbi_wb_nil(&w);            /* reliability: by transport */
    rlbi_wb_u64(&w, ch->qos_depth);
    rlbi_wb_u64(&w, 0);         /* max_age_ms */
    rlbi_wb_u64(&w, ch->redundancy);
    rlbi_wb_bool(&w, false);    /* latest */
    rlbi_wb_bool(&w, ch->flow);
    rlbi_wb_bool(&w, pub);      /* loss_report: the server's first-hop counts, publish only */
    rlbi_wb_str(&w, "volatile", 8);
    return rlbi_ctl_end(k, &w);
}

