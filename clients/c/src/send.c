/* What the client sends: heartbeats, bindings, credit, and the rounds of values taken from the
 * rings (one bundle datagram for all UDP channels, a Batch frame per TCP channel). */
#include <string.h>

#include "conn.h"

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

bool send_tcp_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    tcp_frame_begin(k, &w);
    enc_heartbeat(k, &w, now);
    return tcp_frame_end(k, &w);
}

void send_udp_heartbeat(rlb_conn *k, int64_t now) {
    wbuf w;
    wb_init(&w, k->dg_tx + udp_body_at(k), udp_body_cap(k));
    enc_heartbeat(k, &w, now);
    if (!w.overflow) udp_send(k, w.len);
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
    wb_init(&w, k->dg_tx + udp_body_at(k), udp_body_cap(k));
    if (np > 1) { /* one datagram for the round of every channel (protocol.md 6.16) */
        wb_array(&w, 2);
        wb_u64(&w, T_BUNDLE);
        wb_array(&w, (uint32_t)np);
    }
    for (size_t i = 0; i < np; i++) enc_part(&w, p[i].ch, p[i].n);
    if (w.overflow) return; /* cannot happen: the plan was sized to fit */
    udp_send(k, w.len);
    for (size_t i = 0; i < np; i++) sent(p[i].ch, p[i].n);
}

static bool ready_to_send(const rlb_channel *ch) {
    return ch->dir == DIR_PUBLISH && ch->bind == BIND_ACKED;
}

void send_udp_round(rlb_client *c) {
    rlb_conn *k = c->conn;
    plan p[64];
    size_t np = 0, used = 0, budget = udp_body_cap(k) - 5; /* - the bundle's header */
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

void send_tcp_round(rlb_client *c) {
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
                tcp_frame_begin(k, &w);
                enc_part(&w, ch, take);
                if (tcp_frame_end(k, &w) || take == 1) break;
                take /= 2;
            }
            if (w.overflow) {
                if (k->out_len > 0) break; /* the buffer drains first */
                ring_release(&ch->ring, 1); /* larger than the whole buffer */
                atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
                continue;
            }
            sent(ch, take);
            k->tcp_data = true;
        }
    }
}

/* Credit for flow-controlled subscribe channels: what the ring has room for. */
void send_credits(rlb_client *c) {
    rlb_conn *k = c->conn;
    for (uint32_t j = 0; j < c->n_channels; j++) {
        rlb_channel *ch = c->channels[j];
        if (ch->dir != DIR_SUBSCRIBE || !ch->flow || ch->bind != BIND_ACKED) continue;
        uint64_t consumed = atomic_load_explicit(&ch->n_consumed, memory_order_relaxed);
        uint64_t limit = consumed - ch->credit_base;
        uint64_t step = ch->ring.cap / 4 ? ch->ring.cap / 4 : 1;
        if (limit < ch->credit_sent + step) continue;
        wbuf w;
        tcp_frame_begin(k, &w);
        wb_array(&w, 3);
        wb_u64(&w, T_CREDIT);
        wb_u64(&w, ch->id);
        wb_u64(&w, limit);
        if (tcp_frame_end(k, &w)) ch->credit_sent = limit;
    }
}

/* A control packet: a TCP frame on a TCP session, a datagram on a UDP-only one. */
void ctl_begin(rlb_conn *k, wbuf *w) {
    if (k->tcp >= 0) tcp_frame_begin(k, w);
    else wb_init(w, k->dg_tx + udp_body_at(k), udp_body_cap(k));
}

bool ctl_end(rlb_conn *k, const wbuf *w) {
    if (k->tcp >= 0) return tcp_frame_end(k, w);
    if (w->overflow) return false;
    udp_send(k, w->len);
    return true;
}

bool send_topic_connect(rlb_conn *k, rlb_channel *ch) {
    wbuf w;
    ctl_begin(k, &w);
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
    return ctl_end(k, &w);
}

