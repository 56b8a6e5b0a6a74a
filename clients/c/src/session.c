/*
 * The session's life: one session at a time over a TCP connection (the control transport) and
 * a connected UDP socket (protocol.md 8.1, 8.3): its buffers (allocated once by conn_new), the
 * handshake (16.1), the bindings, one spin (receive, send round, heartbeat, watchdog) and the
 * reconnect with backoff (the goodbye is goodbye.c's). Everything here runs on the thread of
 * rlb_connect / rlb_start / rlb_spin_once, never on the real-time side.
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

#include "conn.h"


rlb_status rlbi_conn_new(rlb_client *c) {
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

void rlbi_conn_close_sockets(rlb_conn *k) {
    rlbi_tls_close(k);
    if (k->tcp >= 0) close(k->tcp);
    if (k->udp >= 0) close(k->udp);
    k->tcp = k->udp = -1;
    k->up = false;
    k->sealed = k->records = false;
    sodium_memzero(&k->keys, sizeof k->keys);
}

void rlbi_conn_free(rlb_client *c) {
    rlb_conn *k = c->conn;
    if (k == NULL) return;
    rlbi_conn_close_sockets(k);
    rlbi_tls_free(c);
    free(k->out), free(k->wire), free(k->in), free(k->rec), free(k->dg_tx), free(k->dg_rx);
    free(k);
    c->conn = NULL;
}

size_t rlbi_conn_pending_bytes(const rlb_conn *k) {
    return k->out_len + (k->wire_len - k->wire_off);
}

size_t rlbi_conn_unsent(rlb_client *c) { return rlbi_conn_pending_bytes(c->conn); }

rlb_channel *rlbi_conn_channel(rlb_client *c, uint64_t id) {
    if (id == 0 || id > c->n_channels) return NULL;
    return c->channels[id - 1];
}

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
    bool tcp = c->cfg.control == RLB_TCP;
    for (struct addrinfo *a = res; a != NULL && rc != RLB_OK; a = a->ai_next) {
        k->tcp = tcp ? socket(a->ai_family, SOCK_STREAM | SOCK_CLOEXEC, 0) : -1;
        k->udp = socket(a->ai_family, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        if ((tcp && (k->tcp < 0 || set_nonblock(k->tcp) < 0)) || k->udp < 0 ||
            set_nonblock(k->udp) < 0 || connect(k->udp, a->ai_addr, a->ai_addrlen) < 0) {
            rlbi_conn_close_sockets(k);
            continue;
        }
        if (!tcp) { /* a UDP-only session (protocol.md 8.2) */
            rc = RLB_OK;
            continue;
        }
        if (connect(k->tcp, a->ai_addr, a->ai_addrlen) < 0 && errno != EINPROGRESS) {
            rlbi_conn_close_sockets(k);
            continue;
        }
        struct pollfd p = {k->tcp, POLLOUT, 0};
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        int err = 0;
        socklen_t el = sizeof err;
        if (left <= 0 || poll(&p, 1, (int)left) != 1 ||
            getsockopt(k->tcp, SOL_SOCKET, SO_ERROR, &err, &el) < 0 || err != 0) {
            rlbi_conn_close_sockets(k);
            continue;
        }
        int one = 1; /* values go out when written, not when Nagle lets them (docs) */
        setsockopt(k->tcp, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        rc = RLB_OK;
    }
    freeaddrinfo(res);
    return rc;
}

static void reset_bindings(rlb_client *c) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        rlb_channel *ch = c->channels[i];
        ch->bind = BIND_NONE;
        ch->next_seq = 0; /* every binding numbers from 0 (protocol.md 10.5) */
        ch->confirmed = 0;
        ch->credit = UINT64_MAX;
        ch->has_highest = false;
        ch->hist_n = ch->hist_at = 0; /* a new binding repeats nothing of the old one */
        atomic_store(&ch->bound, false);
    }
}

static bool spin_io(rlb_client *c, int timeout_ms);

rlb_status rlbi_conn_open(rlb_client *c) {
    rlb_conn *k = c->conn;
    int64_t start = rlb_mono_ns();
    int64_t deadline = start + (int64_t)c->cfg.connect_timeout_ms * 1000000;
    rlbi_conn_close_sockets(k);
    k->out_len = k->wire_off = k->wire_len = k->in_off = k->in_len = k->rec_len = k->skip = 0;
    k->dgram_tx = k->rec_tx = k->rec_rx = k->replay_top = 0;
    memset(k->replay_bits, 0, sizeof k->replay_bits);
    k->peer_sent = k->peer_wall = k->srtt = k->rttvar = 0;
    reset_bindings(c);
    rlb_status rc = open_sockets(c, deadline);
    if (rc == RLB_OK && c->cfg.tls) rc = rlbi_tls_connect(c, deadline);
    if (rc == RLB_OK)
        rc = c->cfg.control == RLB_UDP ? rlbi_handshake_udp(c, deadline)
                                       : rlbi_handshake_tcp(c, deadline);
    if (rc != RLB_OK) {
        rlbi_conn_close_sockets(k);
        return rc;
    }
    k->up = true;
    k->last_rx = k->last_hb = rlb_mono_ns();
    rlbi_send_udp_heartbeat(k, k->last_hb); /* registers our UDP address (protocol.md 8.3) */
    int64_t resend = 0;
    for (uint32_t i = 0; i < c->n_channels; i++) c->channels[i]->bind = BIND_SENT;
    for (;;) {
        if (rlb_mono_ns() >= resend) { /* once over TCP; over UDP until answered (9) */
            for (uint32_t i = 0; i < c->n_channels; i++) {
                if (c->channels[i]->bind != BIND_SENT) continue;
                if (!rlbi_send_topic_connect(k, c->channels[i])) {
                    rlbi_conn_close_sockets(k);
                    return RLB_E_NOMEM; /* more bindings than the TCP buffer holds */
                }
            }
            resend = k->tcp >= 0 ? INT64_MAX : rlb_mono_ns() + 250000000;
        }
        bool pending = false, refused = false;
        for (uint32_t i = 0; i < c->n_channels; i++) {
            pending |= c->channels[i]->bind == BIND_SENT;
            refused |= c->channels[i]->bind == BIND_REFUSED;
        }
        if (!pending) {
            if (refused && !c->connected_once) {
                rlbi_conn_close_sockets(k);
                return RLB_E_REFUSED;
            }
            break;
        }
        int64_t now = rlb_mono_ns(), left = (deadline - now) / 1000000;
        /* a slow binding (a ROS type to load) must not starve the server's watchdog */
        if (now >= k->last_hb + (int64_t)k->hb_ms * 1000000) {
            k->last_hb = now;
            if (k->tcp >= 0) rlbi_send_tcp_heartbeat(k, now);
            rlbi_send_udp_heartbeat(k, now);
        }
        if (left <= 0 || !spin_io(c, (int)(left < 50 ? left : 50)) || !k->up) {
            rlbi_conn_close_sockets(k);
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

/* The next attempt: the backoff, +-20 % jitter so that clients of one server spread out. */
static void schedule_retry(rlb_client *c) {
    rlb_conn *k = c->conn;
    uint32_t b = k->backoff_ms ? k->backoff_ms : 1;
    uint64_t jitter = next_random(c) % (b / 5 * 2 + 1);
    k->retry_at = rlb_mono_ns() + (int64_t)(b - b / 5 + jitter) * 1000000;
}

void rlbi_conn_lost(rlb_client *c, const char *why) {
    rlb_conn *k = c->conn;
    (void)why;
    if (!k->up) return;
    rlbi_conn_close_sockets(k);
    if (k->bye) return; /* the goodbye's end (goodbye.c): its bindings are still counted */
    reset_bindings(c);
    rlb_set_link(c, RLB_LINK_LOST);
    if (!c->cfg.reconnect) {
        k->closed = true;
        return;
    }
    schedule_retry(c);
}

/* Receives (waiting up to timeout_ms) and dispatches; false when the session broke. */
static bool spin_io(rlb_client *c, int timeout_ms) {
    rlb_conn *k = c->conn;
    if (!rlbi_tcp_flush(k)) {
        rlbi_conn_lost(c, "send failed");
        return false;
    }
    struct pollfd p[2] = {{k->tcp, POLLIN, 0}, {k->udp, POLLIN, 0}};
    if (k->wire_off < k->wire_len) p[0].events |= POLLOUT;
    bool held = rlbi_tls_pending(k); /* bytes TLS has decrypted already: no wait for them */
    int r = poll(p, 2, held ? 0 : timeout_ms);
    if (r < 0 && errno != EINTR) return true;
    if (held) p[0].revents |= POLLIN;
    if (p[0].revents & (POLLIN | POLLHUP | POLLERR)) {
        bool ok = rlbi_tcp_read(k);
        for (;;) {
            size_t len;
            bool bad;
            const uint8_t *f = rlbi_tcp_next_frame(k, &len, &bad);
            if (bad) ok = false;
            if (f == NULL || !k->up) break;
            if (len > 1 && (f[1] == T_VALUE || f[1] == T_BATCH)) k->tcp_data = true;
            rlbi_conn_packet(c, f, len, false);
        }
        if (!ok && k->up) {
            rlbi_conn_lost(c, "connection closed");
            return false;
        }
    }
    if (k->up && (p[1].revents & POLLIN)) rlbi_udp_read(c);
    return k->up;
}

rlb_status rlbi_conn_spin(rlb_client *c, uint32_t timeout_ms) {
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
        if (rlbi_conn_open(c) != RLB_OK) {
            rlb_set_link(c, RLB_LINK_LOST);
            uint32_t b = k->backoff_ms * 2;
            k->backoff_ms = b > c->cfg.backoff_max_ms ? c->cfg.backoff_max_ms : b;
            schedule_retry(c);
        }
        return RLB_OK;
    }
    int64_t next_hb = k->last_hb + (int64_t)k->hb_ms * 1000000;
    int64_t until = (next_hb - now) / 1000000;
    if (until < 0) until = 0;
    int wait = (int)(until < (int64_t)timeout_ms ? until : (int64_t)timeout_ms);
    if (!spin_io(c, wait)) return RLB_OK;
    rlbi_send_udp_round(c);
    rlbi_send_tcp_round(c);
    rlbi_send_credits(c);
    now = rlb_mono_ns();
    if (now >= next_hb) {
        k->last_hb = now;
        /* Not amid a TCP stream: a heartbeat segment there would put the peer's kernel into
         * delayed-ACK mode (protocol.md 11); the UDP heartbeat and the data prove liveness. */
        if (!k->tcp_data && k->tcp >= 0) rlbi_send_tcp_heartbeat(k, now);
        k->tcp_data = false;
        rlbi_send_udp_heartbeat(k, now);
    }
    int64_t silence = now - k->last_rx;
    if (silence >= (int64_t)k->timeout_ms * 1000000 && !k->bye) { /* the goodbye has a bound */
        rlbi_conn_lost(c, "watchdog: the server is silent");
        return RLB_OK;
    }
    rlb_set_link(c, silence * 2 < (int64_t)k->hb_ms * 3000000 ? RLB_LINK_CONNECTED
                                                               : RLB_LINK_DEGRADED);
    if (!rlbi_tcp_flush(k)) rlbi_conn_lost(c, "send failed");
    return RLB_OK;
}
