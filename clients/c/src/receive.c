/* What the client receives: packets decoded by the cursor and dispatched to channels (values
 * by the sequence rule of protocol.md 10.2), counters and events; entry points for tests. */
#include <stdio.h>
#include <string.h>

#include "conn.h"

/* -- packets we receive -------------------------------------------------------------------- */

void rlbi_conn_malformed(rlb_conn *k) { k->malformed++; }

static void deliver(rlb_channel *ch, uint64_t seq, int64_t stamp, const uint8_t *v, size_t len) {
    if (ch->has_highest && seq <= ch->highest) {
        atomic_fetch_add_explicit(&ch->n_duplicates, 1, memory_order_relaxed);
        return;
    }
    if (ch->has_highest && seq > ch->highest + 1)
        atomic_fetch_add_explicit(&ch->n_lost, seq - ch->highest - 1, memory_order_relaxed);
    ch->has_highest = true;
    ch->highest = seq;
    rlbi_chan_deliver(ch, stamp, v, len);
}

/* A Value or Batch body (tag already read). */
static bool values(rlb_client *c, mp_cur *m, uint64_t tag) {
    uint64_t id, seq;
    if (!rlbi_mp_u64(m, &id) || !rlbi_mp_u64(m, &seq)) return false;
    rlb_channel *ch = rlbi_conn_channel(c, id);
    /* BIND_SENT too: over UDP a value can overtake the TopicAck that travels over TCP */
    bool ours = ch != NULL && ch->dir == DIR_SUBSCRIBE &&
                (ch->bind == BIND_ACKED || ch->bind == BIND_SENT);
    if (tag == T_VALUE) {
        int64_t stamp;
        if (!rlbi_mp_i64(m, &stamp)) return false;
        const uint8_t *v = m->p;
        if (!rlbi_mp_skip(m)) return false;
        if (ours) deliver(ch, seq, stamp, v, (size_t)(m->p - v));
        return true;
    }
    uint32_t ns, nv;
    if (!rlbi_mp_array(m, &ns)) return false;
    mp_cur stamps = *m;
    for (uint32_t i = 0; i < ns; i++) {
        int64_t st;
        if (!rlbi_mp_i64(m, &st)) return false;
    }
    if (!rlbi_mp_array(m, &nv) || nv != ns) return false;
    for (uint32_t i = 0; i < nv; i++) {
        int64_t stamp;
        rlbi_mp_i64(&stamps, &stamp);
        const uint8_t *v = m->p;
        if (!rlbi_mp_skip(m)) return false;
        if (ours) deliver(ch, seq + i, stamp, v, (size_t)(m->p - v));
    }
    return true;
}

static void on_error(rlb_client *c, mp_cur *m, bool topic) {
    uint64_t code = 0, id = 0;
    const char *reason = "";
    uint32_t rlen = 0;
    char text[256];
    if (topic) { /* TopicError [6, channel, code, reason] */
        if (!rlbi_mp_u64(m, &id) || !rlbi_mp_u64(m, &code)) {
            rlbi_conn_malformed(c->conn);
            return;
        }
        rlbi_mp_str(m, &reason, &rlen);
    } else {     /* Error [12, code, reason, channel|nil, values] */
        if (!rlbi_mp_u64(m, &code)) { rlbi_conn_malformed(c->conn); return; }
        if (rlbi_mp_str(m, &reason, &rlen) && !rlbi_mp_nil(m)) rlbi_mp_u64(m, &id);
    }
    snprintf(text, sizeof text, "%.*s", (int)(rlen < 255 ? rlen : 255), reason);
    rlb_channel *ch = rlbi_conn_channel(c, id);
    if (ch != NULL) {
        atomic_fetch_add_explicit(&ch->n_errors, 1, memory_order_relaxed);
        atomic_store_explicit(&ch->last_error, (int)code, memory_order_relaxed);
        if (topic) ch->bind = BIND_REFUSED;
    }
    rlb_emit(c, topic ? RLB_EV_TOPIC_ERROR : RLB_EV_ERROR, (int)code, (uint32_t)id, text);
}

static void dispatch(rlb_client *c, mp_cur *m, uint64_t tag, bool in_bundle) {
    rlb_conn *k = c->conn;
    int64_t now = rlb_mono_ns();
    if (in_bundle && tag != T_VALUE && tag != T_BATCH) { rlbi_conn_malformed(k); return; }
    switch (tag) {
    case T_VALUE:
    case T_BATCH:
        if (!values(c, m, tag)) rlbi_conn_malformed(k);
        break;
    case T_TOPICACK: {
        uint64_t id, credit = UINT64_MAX;
        const char *type;
        uint32_t tl;
        if (!rlbi_mp_u64(m, &id) || !rlbi_mp_str(m, &type, &tl)) { rlbi_conn_malformed(k); return; }
        /* initial, schema, then the credit of a flow-controlled publish channel */
        if (rlbi_mp_skip(m) && rlbi_mp_skip(m) && !rlbi_mp_nil(m)) rlbi_mp_u64(m, &credit);
        rlb_channel *ch = rlbi_conn_channel(c, id);
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
        if (!rlbi_mp_i64(m, &sent_ns)) { rlbi_conn_malformed(k); return; }
        bool has_echo = rlbi_mp_i64(m, &echo);
        if (has_echo && rlbi_mp_i64(m, &wall)) {
            k->peer_wall = wall;
            k->peer_wall_rx = rlb_wall_ns();
        }
        if (has_echo && echo > 0 && echo <= now) { /* our sent_ns, aged by the peer (11) */
            int64_t sample = now - echo;
            if (k->srtt == 0) {
                k->srtt = sample;
                k->rttvar = sample / 2;
            } else {
                int64_t d = k->srtt > sample ? k->srtt - sample : sample - k->srtt;
                k->rttvar += (d - k->rttvar) / 4;
                k->srtt += (sample - k->srtt) / 8;
            }
            atomic_store_explicit(&c->rtt_ns, k->srtt, memory_order_relaxed);
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
        if (rlbi_mp_u64(m, &code)) rlbi_mp_str(m, &reason, &rl);
        snprintf(text, sizeof text, "%.*s", (int)(rl < 255 ? rl : 255), reason);
        rlb_emit(c, RLB_EV_DISCONNECT, (int)code, 0, text);
        rlbi_conn_lost(c, text);
        return;
    }
    case T_BUNDLE: {
        uint32_t n;
        if (!rlbi_mp_array(m, &n)) { rlbi_conn_malformed(k); return; }
        for (uint32_t i = 0; i < n; i++) {
            const uint8_t *part = m->p;
            if (!rlbi_mp_skip(m)) { rlbi_conn_malformed(k); return; }
            rlbi_conn_packet(c, part, (size_t)(m->p - part), true);
        }
        break;
    }
    case T_CREDIT: {
        uint64_t id, limit;
        if (!rlbi_mp_u64(m, &id) || !rlbi_mp_u64(m, &limit)) { rlbi_conn_malformed(k); return; }
        rlb_channel *ch = rlbi_conn_channel(c, id);
        bool more = ch && ch->dir == DIR_PUBLISH && ch->flow; /* cumulative: only raises */
        if (more && (ch->credit == UINT64_MAX || limit > ch->credit))
            ch->credit = limit;
        break;
    }
    case T_LOSS: {
        uint32_t n, f;
        if (!rlbi_mp_array(m, &n)) { rlbi_conn_malformed(k); return; }
        for (uint32_t i = 0; i < n; i++) {
            uint64_t id, received, lost, next_seq;
            if (!rlbi_mp_array(m, &f) || f < 4 || !rlbi_mp_u64(m, &id) ||
                !rlbi_mp_u64(m, &received) || !rlbi_mp_u64(m, &lost) ||
                !rlbi_mp_u64(m, &next_seq)) {
                rlbi_conn_malformed(k);
                return;
            }
            for (uint32_t j = 4; j < f; j++)
                if (!rlbi_mp_skip(m)) { rlbi_conn_malformed(k); return; }
            rlb_channel *ch = rlbi_conn_channel(c, id);
            if (ch && ch->dir == DIR_PUBLISH) {
                atomic_store_explicit(&ch->n_srv_received, received, memory_order_relaxed);
                atomic_store_explicit(&ch->n_lost, lost, memory_order_relaxed);
                if (next_seq > ch->confirmed) ch->confirmed = next_seq; /* UDP: reordered */
            }
        }
        break;
    }
    default: /* Stats, RosLoss, service packets, a late ConnectAck: nothing to do */
        break;
    }
}

void rlbi_conn_packet(rlb_client *c, const uint8_t *body, size_t len, bool in_bundle) {
    mp_cur m;
    uint32_t n;
    uint64_t tag;
    rlbi_mp_init(&m, body, len);
    if (!rlbi_mp_array(&m, &n) || n < 1 || !rlbi_mp_u64(&m, &tag)) {
        rlbi_conn_malformed(c->conn);
        return;
    }
    if (!in_bundle) c->conn->last_rx = rlb_mono_ns();
    dispatch(c, &m, tag, in_bundle);
}

/* -- test and fuzz entry points: bytes as if received, no socket -------------------------- */

void rlb_debug_bind_all(rlb_client *c, uint64_t token) {
    c->conn->token = token;
    for (uint32_t i = 0; i < c->n_channels; i++) c->channels[i]->bind = BIND_ACKED;
}

void rlb_debug_feed_datagram(rlb_client *c, const uint8_t *d, size_t n) {
    if (n > RX_DGRAM) return;
    memcpy(c->conn->dg_rx, d, n);
    rlbi_udp_datagram(c, c->conn->dg_rx, n);
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
            const uint8_t *f = rlbi_tcp_next_frame(k, &len, &bad);
            if (bad) { /* the framing is lost: a real connection would end here */
                k->in_off = k->in_len = k->skip = 0;
                break;
            }
            if (f == NULL) break;
            rlbi_conn_packet(c, f, len, false);
        }
    }
}

uint64_t rlb_debug_malformed(const rlb_client *c) { return c->conn->malformed; }

