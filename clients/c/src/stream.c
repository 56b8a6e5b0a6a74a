/* The TCP byte stream: frames (protocol.md 2) and, on a keyed session, sealed records (16.5). */
#include <errno.h>
#include <poll.h>
#include <string.h>
#include <sys/socket.h>

#include "conn.h"

/* -- TCP output -------------------------------------------------------------------------- */

/* Starts a frame: the body is written into w; tcp_frame_end commits it (false: no room). */
void rlbi_tcp_frame_begin(rlb_conn *k, wbuf *w) {
    size_t room = k->cap > k->out_len + 8 ? k->cap - k->out_len - 8 : 0;
    rlbi_wb_init(w, k->out + k->out_len + 8, room);
    if (room == 0) w->overflow = true;
}

bool rlbi_tcp_frame_end(rlb_conn *k, const wbuf *w) {
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
    if (!k->records) {
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
bool rlbi_tcp_flush(rlb_conn *k) {
    for (int i = 0; i < 4; i++) {
        stage(k);
        if (k->wire_off >= k->wire_len) return true;
        ssize_t n = rlbi_stream_send(k, k->wire + k->wire_off, k->wire_len - k->wire_off);
        if (n < 0) return errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR;
        k->wire_off += (size_t)n;
        if (k->wire_off == k->wire_len) k->wire_off = k->wire_len = 0;
    }
    return true;
}

bool rlbi_tcp_flush_blocking(rlb_conn *k, int64_t deadline) {
    while (rlbi_conn_pending_bytes(k) > 0) {
        if (!rlbi_tcp_flush(k)) return false;
        if (k->out_len == 0 && k->wire_off >= k->wire_len) break;
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if (left <= 0) return false;
        struct pollfd p = {k->tcp, POLLOUT, 0};
        poll(&p, 1, (int)left);
    }
    return true;
}

/* -- TCP input ----------------------------------------------------------------------------- */

/* Opens complete sealed records from rec into in; false: the stream cannot be trusted. */
bool rlbi_tcp_open_records(rlb_conn *k) {
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
bool rlbi_tcp_read(rlb_conn *k) {
    for (int i = 0; i < 8; i++) {
        ssize_t n;
        if (k->records) {
            size_t room = RECORD_MAX + 24 + 8 - k->rec_len;
            if (room == 0) return rlbi_tcp_open_records(k);
            n = rlbi_stream_recv(k, k->rec + k->rec_len, room);
            if (n > 0) {
                k->rec_len += (size_t)n;
                if (!rlbi_tcp_open_records(k)) return false;
            }
        } else {
            if (k->in_off > 0) {
                memmove(k->in, k->in + k->in_off, k->in_len - k->in_off);
                k->in_len -= k->in_off;
                k->in_off = 0;
            }
            if (k->in_len == k->cap) return true;
            n = rlbi_stream_recv(k, k->in + k->in_len, k->cap - k->in_len);
            if (n > 0) k->in_len += (size_t)n;
        }
        if (n == 0) return false;
        if (n < 0) return errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR;
    }
    return true;
}

/* The next complete frame's body in in, or NULL; consumed by the caller via in_off. A frame
 * larger than the buffer is skipped (counted malformed); -1 in *bad: the framing is lost. */
const uint8_t *rlbi_tcp_next_frame(rlb_conn *k, size_t *len, bool *bad) {
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
        rlbi_conn_malformed(k);
        return rlbi_tcp_next_frame(k, len, bad);
    }
    if (k->in_len - k->in_off < 8 + n) return NULL;
    k->in_off += 8 + n;
    *len = n;
    return h + 8;
}

