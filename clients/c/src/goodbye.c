/*
 * rlb_close's goodbye: the server takes the session's last values before it ends (protocol.md
 * 8.4 "Last values", the rule the Python SDK's Bridge.close follows too).
 *
 * Why. The server reads TCP and UDP independently: a Disconnect over TCP can be handled before
 * datagrams sent ahead of it (then dropped: dead token), and one over UDP discards TCP frames
 * it has not read yet. What is in flight is known per publish channel: the values numbered in
 * this binding beyond the next_seq of the server's last LossReport (every publish channel asks
 * for reports). Everything here runs on the I/O side, after the I/O thread stopped; the
 * real-time side is not involved (no lock, no system call there).
 *
 *  1. Flush: send rounds until the rings the real-time side wrote are empty.
 *  2. Nothing unconfirmed over UDP: Disconnect over TCP, behind the TCP values (in order).
 *  3. TCP values unconfirmed too: wait for loss reports to cover them first (a goodbye over
 *     UDP would overtake them).
 *  4. UDP values unconfirmed: Disconnect over UDP, behind them on the same socket, resent
 *     every two round trips (at most a heartbeat period) until the server closes TCP, which
 *     it does on handling it.
 * Bound: the session's timeout_ms (ConnectAck), at most connect_timeout_ms. At the bound the
 * goodbye goes over TCP, and what the server never confirmed on a UDP channel (and what never
 * left a ring) is added to the channel's lost count and reported (RLB_EV_UNCONFIRMED).
 */
#include <poll.h>
#include <stdio.h>
#include <sys/socket.h>

#include "conn.h"

/* Values of ch sent in this binding that no LossReport confirmed. */
static uint64_t unconfirmed(const rlb_channel *ch) {
    return ch->next_seq > ch->confirmed ? ch->next_seq - ch->confirmed : 0;
}

static bool waiting(const rlb_client *c, rlb_transport transport) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        const rlb_channel *ch = c->channels[i];
        if (ch->dir == DIR_PUBLISH && ch->transport == transport && unconfirmed(ch) > 0)
            return true;
    }
    return false;
}

static bool unsent(const rlb_client *c) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        const rlb_channel *ch = c->channels[i];
        if (ch->dir == DIR_PUBLISH && ch->bind == BIND_ACKED && rlbi_ring_count(&ch->ring) > 0)
            return true;
    }
    return rlbi_conn_pending_bytes(c->conn) > 0;
}

/* How long to wait for an answer before asking again: two round trips, 10 ms .. a heartbeat
 * period (a quarter of one while the round trip is unknown). */
static int slice_ms(const rlb_conn *k) {
    if (k->srtt <= 0) return (int)(k->hb_ms / 4 ? k->hb_ms / 4 : 1);
    int64_t ms = 2 * k->srtt / 1000000;
    if (ms < 10) ms = 10;
    return (int)(ms > (int64_t)k->hb_ms ? (int64_t)k->hb_ms : ms);
}

/* One spin of the session (receive, send rounds, heartbeats), up to ms; false once the
 * session ended (the server closed TCP, or the link broke) or the deadline passed. */
static bool spin_until(rlb_client *c, int64_t deadline, int ms) {
    rlb_conn *k = c->conn;
    int64_t left = (deadline - rlb_mono_ns()) / 1000000;
    if (!k->up || left <= 0) return false;
    rlbi_conn_spin(c, (uint32_t)(left < ms ? left : ms));
    return k->up;
}

/* Every value the server never confirmed on the channels that lose them (UDP ones; any
 * channel's values still in its ring): counted in lost, and said. */
static void count_unconfirmed(rlb_client *c, const char *when) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        rlb_channel *ch = c->channels[i];
        if (ch->dir != DIR_PUBLISH) continue;
        uint64_t n = rlbi_ring_count(&ch->ring);
        if (ch->transport == RLB_UDP) n += unconfirmed(ch);
        if (n == 0) continue;
        atomic_fetch_add_explicit(&ch->n_unconfirmed, n, memory_order_relaxed);
        char text[200];
        snprintf(text, sizeof text,
                 "closing: the server did not confirm the last %llu value(s) of %s %s; "
                 "counted as lost", (unsigned long long)n, ch->topic, when);
        rlb_emit(c, RLB_EV_UNCONFIRMED, (int)(n > 0x7fffffff ? 0x7fffffff : n), ch->id, text);
    }
}

static size_t enc_disconnect(wbuf *w) {
    rlbi_wb_array(w, 3);
    rlbi_wb_u64(w, T_DISCONNECT);
    rlbi_wb_u64(w, 0);
    rlbi_wb_str(w, "bye", 3);
    return w->len;
}

static void udp_goodbye(rlb_conn *k) {
    wbuf w;
    rlbi_wb_init(&w, k->dg_tx + rlbi_udp_body_at(k), rlbi_udp_body_cap(k));
    rlbi_udp_send(k, enc_disconnect(&w));
}

/* Disconnect over TCP, behind the TCP values; flushed within `ms` (the bound may be over). */
static void tcp_goodbye(rlb_conn *k, uint32_t ms) {
    wbuf w;
    rlbi_tcp_frame_begin(k, &w);
    enc_disconnect(&w);
    rlbi_tcp_frame_end(k, &w);
    rlbi_tcp_flush_blocking(k, rlb_mono_ns() + (int64_t)ms * 1000000);
}

/* Disconnect over UDP, resent, until the server hangs up TCP; false at the deadline. */
static bool over_udp(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    for (;;) {
        udp_goodbye(k);
        int64_t resend = rlb_mono_ns() + (int64_t)slice_ms(k) * 1000000;
        while (rlb_mono_ns() < resend)
            if (!spin_until(c, deadline, (int)((resend - rlb_mono_ns()) / 1000000) + 1))
                return !k->up;
    }
}

/* Waits for loss reports covering every TCP value; false at the deadline or session end. */
static bool tcp_covered(rlb_client *c, int64_t deadline) {
    while (waiting(c, RLB_TCP))
        if (!spin_until(c, deadline, slice_ms(c->conn))) return !waiting(c, RLB_TCP);
    return true;
}

void rlbi_conn_goodbye(rlb_client *c) {
    rlb_conn *k = c->conn;
    if (k == NULL || !k->up) return;
    k->bye = true; /* the session's end from here on is the goodbye, not a lost link */
    uint32_t ms = k->timeout_ms < c->cfg.connect_timeout_ms ? k->timeout_ms
                                                              : c->cfg.connect_timeout_ms;
    int64_t deadline = rlb_mono_ns() + (int64_t)ms * 1000000;
    char within[48];
    snprintf(within, sizeof within, "within %u ms", (unsigned)ms);
    while (unsent(c) && spin_until(c, deadline, 1)) {
    }
    if (!k->up) {
        count_unconfirmed(c, "before the session ended");
    } else if (k->tcp < 0) { /* UDP-only: the goodbye is a datagram behind the values */
        udp_goodbye(k);
    } else if (!waiting(c, RLB_UDP)) {
        count_unconfirmed(c, within); /* only values a ring still holds (no credit) */
        tcp_goodbye(k, ms);
    } else if (!tcp_covered(c, deadline)) {
        count_unconfirmed(c, k->up ? within : "before the session ended");
        if (k->up) tcp_goodbye(k, ms); /* behind the TCP values, which it keeps */
    } else if (waiting(c, RLB_UDP) && !over_udp(c, deadline)) {
        count_unconfirmed(c, within);
        tcp_goodbye(k, ms);
    } else if (k->up) { /* the reports that covered TCP covered UDP too */
        tcp_goodbye(k, ms);
    }
    if (k->tcp >= 0) shutdown(k->tcp, SHUT_WR);
    rlbi_conn_close_sockets(k);
}
