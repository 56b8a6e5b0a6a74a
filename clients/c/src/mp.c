/*
 * MessagePack for the wire (protocol.md sections 4-5).
 *
 * Encoding goes through msgpack-c's packer (static inline functions in msgpack/pack.h) with a
 * write callback into a fixed buffer: no allocation, so it also runs on the real-time side.
 * Decoding is a cursor over the received bytes, written here rather than taken from
 * msgpack-c: msgpack-c's unpacker builds an object tree in a zone it allocates with malloc,
 * and a decoder fed by the network should neither allocate per packet nor recurse on
 * attacker-chosen nesting. Every read checks the bounds; a short or wrong input sets err.
 */
#include <msgpack.h>
#include <string.h>

#include "internal.h"

void rlbi_mp_init(mp_cur *c, const void *data, size_t len) {
    c->p = data;
    c->end = c->p + len;
    c->err = false;
}

static bool need(mp_cur *c, size_t n) {
    if (c->err || (size_t)(c->end - c->p) < n) {
        c->err = true;
        return false;
    }
    return true;
}

static uint64_t be(const uint8_t *p, int n) {
    uint64_t v = 0;
    for (int i = 0; i < n; i++) v = (v << 8) | p[i];
    return v;
}

static bool take_len(mp_cur *c, int n, uint32_t *len) {
    if (!need(c, 1 + (size_t)n)) return false;
    *len = (uint32_t)be(c->p + 1, n);
    c->p += 1 + n;
    return true;
}

bool rlbi_mp_array(mp_cur *c, uint32_t *n) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    if ((t & 0xf0) == 0x90) {
        *n = t & 0x0f;
        c->p++;
        return true;
    }
    if (t == 0xdc) return take_len(c, 2, n);
    if (t == 0xdd) return take_len(c, 4, n);
    c->err = true;
    return false;
}

bool rlbi_mp_map(mp_cur *c, uint32_t *n) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    if ((t & 0xf0) == 0x80) {
        *n = t & 0x0f;
        c->p++;
        return true;
    }
    if (t == 0xde) return take_len(c, 2, n);
    if (t == 0xdf) return take_len(c, 4, n);
    c->err = true;
    return false;
}

bool rlbi_mp_is_int(const mp_cur *c) {
    if (c->err || c->p >= c->end) return false;
    uint8_t t = *c->p;
    return t <= 0x7f || t >= 0xe0 || (t >= 0xcc && t <= 0xcf) || (t >= 0xd0 && t <= 0xd3);
}

/* An integer as sign + magnitude bits: returns false if not an integer. */
static bool read_int(mp_cur *c, bool *negative, uint64_t *u) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    *negative = false;
    if (t <= 0x7f) {
        *u = t;
        c->p++;
        return true;
    }
    if (t >= 0xe0) {
        *negative = true;
        *u = (uint64_t)(int64_t)(int8_t)t;
        c->p++;
        return true;
    }
    int n;
    bool sign;
    switch (t) {
    case 0xcc: n = 1; sign = false; break;
    case 0xcd: n = 2; sign = false; break;
    case 0xce: n = 4; sign = false; break;
    case 0xcf: n = 8; sign = false; break;
    case 0xd0: n = 1; sign = true; break;
    case 0xd1: n = 2; sign = true; break;
    case 0xd2: n = 4; sign = true; break;
    case 0xd3: n = 8; sign = true; break;
    default: c->err = true; return false;
    }
    if (!need(c, 1 + (size_t)n)) return false;
    uint64_t v = be(c->p + 1, n);
    c->p += 1 + n;
    if (sign && n < 8 && (v >> (8 * n - 1)) & 1) v |= ~0ULL << (8 * n); /* sign-extend */
    *negative = sign && (int64_t)v < 0;
    *u = v;
    return true;
}

bool rlbi_mp_u64(mp_cur *c, uint64_t *v) {
    bool neg;
    if (!read_int(c, &neg, v)) return false;
    if (neg) c->err = true;
    return !neg;
}

bool rlbi_mp_i64(mp_cur *c, int64_t *v) {
    bool neg;
    uint64_t u;
    if (!read_int(c, &neg, &u)) return false;
    if (!neg && u > (uint64_t)INT64_MAX) {
        c->err = true;
        return false;
    }
    *v = (int64_t)u;
    return true;
}

bool rlbi_mp_f64(mp_cur *c, double *v) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    if (t == 0xcb) {
        if (!need(c, 9)) return false;
        uint64_t bits = be(c->p + 1, 8);
        memcpy(v, &bits, 8);
        c->p += 9;
        return true;
    }
    if (t == 0xca) {
        if (!need(c, 5)) return false;
        uint32_t bits = (uint32_t)be(c->p + 1, 4);
        float f;
        memcpy(&f, &bits, 4);
        *v = f;
        c->p += 5;
        return true;
    }
    bool neg;
    uint64_t u;
    if (!read_int(c, &neg, &u)) return false;
    *v = neg ? (double)(int64_t)u : (double)u;
    return true;
}

bool rlbi_mp_bool(mp_cur *c, bool *v) {
    if (!need(c, 1)) return false;
    if (*c->p != 0xc2 && *c->p != 0xc3) {
        c->err = true;
        return false;
    }
    *v = *c->p == 0xc3;
    c->p++;
    return true;
}

bool rlbi_mp_nil(mp_cur *c) {
    if (c->err || c->p >= c->end || *c->p != 0xc0) return false;
    c->p++;
    return true;
}

static bool body(mp_cur *c, uint32_t len, const uint8_t **b) {
    if (!need(c, len)) return false;
    *b = c->p;
    c->p += len;
    return true;
}

bool rlbi_mp_str(mp_cur *c, const char **s, uint32_t *len) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    if ((t & 0xe0) == 0xa0) {
        *len = t & 0x1f;
        c->p++;
    } else if (t == 0xd9) {
        if (!take_len(c, 1, len)) return false;
    } else if (t == 0xda) {
        if (!take_len(c, 2, len)) return false;
    } else if (t == 0xdb) {
        if (!take_len(c, 4, len)) return false;
    } else {
        c->err = true;
        return false;
    }
    const uint8_t *b = NULL; /* not through a cast: char* and uint8_t* must not alias */
    if (!body(c, *len, &b)) return false;
    *s = (const char *)b;
    return true;
}

bool rlbi_mp_bin(mp_cur *c, const uint8_t **b, uint32_t *len) {
    if (!need(c, 1)) return false;
    uint8_t t = *c->p;
    int n = t == 0xc4 ? 1 : t == 0xc5 ? 2 : t == 0xc6 ? 4 : 0;
    if (n == 0) {
        c->err = true;
        return false;
    }
    if (!take_len(c, n, len)) return false;
    return body(c, *len, b);
}

bool rlbi_mp_skip(mp_cur *c) {
    uint64_t todo = 1;
    while (todo > 0) {
        if (!need(c, 1)) return false;
        if (todo > (uint64_t)(c->end - c->p)) { /* every element takes at least one byte */
            c->err = true;
            return false;
        }
        todo--;
        uint8_t t = *c->p;
        uint32_t n = 0;
        if (t <= 0x7f || t >= 0xe0 || t == 0xc0 || t == 0xc2 || t == 0xc3) {
            c->p++;
        } else if ((t & 0xf0) == 0x80 || t == 0xde || t == 0xdf) {
            if (!rlbi_mp_map(c, &n)) return false;
            todo += 2ULL * n;
        } else if ((t & 0xf0) == 0x90 || t == 0xdc || t == 0xdd) {
            if (!rlbi_mp_array(c, &n)) return false;
            todo += n;
        } else if ((t & 0xe0) == 0xa0 || (t >= 0xd9 && t <= 0xdb)) {
            const char *s;
            if (!rlbi_mp_str(c, &s, &n)) return false;
        } else if (t >= 0xc4 && t <= 0xc6) {
            const uint8_t *b;
            if (!rlbi_mp_bin(c, &b, &n)) return false;
        } else if (t == 0xca || t == 0xcb) {
            double d;
            if (!rlbi_mp_f64(c, &d)) return false;
        } else if ((t >= 0xcc && t <= 0xcf) || (t >= 0xd0 && t <= 0xd3)) {
            bool neg;
            uint64_t u;
            if (!read_int(c, &neg, &u)) return false;
        } else if (t >= 0xd4 && t <= 0xd8) { /* fixext */
            static const uint8_t sizes[] = {1, 2, 4, 8, 16};
            if (!need(c, 2 + (size_t)sizes[t - 0xd4])) return false;
            c->p += 2 + sizes[t - 0xd4];
        } else if (t >= 0xc7 && t <= 0xc9) { /* ext 8/16/32 */
            int w = t == 0xc7 ? 1 : t == 0xc8 ? 2 : 4;
            if (!take_len(c, w, &n) || !need(c, 1 + (size_t)n)) return false;
            c->p += 1 + n;
        } else { /* 0xc1: never used */
            c->err = true;
            return false;
        }
    }
    return !c->err;
}

/* -- encoding --------------------------------------------------------------------------- */

static int wb_write(void *data, const char *buf, size_t len) {
    wbuf *w = data;
    if (w->overflow || w->cap - w->len < len) {
        w->overflow = true;
        return -1;
    }
    memcpy(w->buf + w->len, buf, len);
    w->len += len;
    return 0;
}

#define PACKER(w) \
    msgpack_packer pk; \
    msgpack_packer_init(&pk, (w), wb_write)

void rlbi_wb_init(wbuf *w, void *buf, size_t cap) {
    w->buf = buf;
    w->cap = cap;
    w->len = 0;
    w->overflow = false;
}
void rlbi_wb_array(wbuf *w, uint32_t n) { PACKER(w); msgpack_pack_array(&pk, n); }
void rlbi_wb_map(wbuf *w, uint32_t n) { PACKER(w); msgpack_pack_map(&pk, n); }
void rlbi_wb_u64(wbuf *w, uint64_t v) { PACKER(w); msgpack_pack_uint64(&pk, v); }
void rlbi_wb_i64(wbuf *w, int64_t v) { PACKER(w); msgpack_pack_int64(&pk, v); }
void rlbi_wb_f64(wbuf *w, double v) { PACKER(w); msgpack_pack_double(&pk, v); }
void rlbi_wb_bool(wbuf *w, bool v) {
    PACKER(w);
    if (v) msgpack_pack_true(&pk);
    else msgpack_pack_false(&pk);
}
void rlbi_wb_nil(wbuf *w) { PACKER(w); msgpack_pack_nil(&pk); }
void rlbi_wb_str(wbuf *w, const char *s, size_t len) {
    PACKER(w);
    msgpack_pack_str_with_body(&pk, s, len);
}
void rlbi_wb_bin(wbuf *w, const uint8_t *b, size_t len) {
    PACKER(w);
    msgpack_pack_bin_with_body(&pk, b, len);
}
void rlbi_wb_raw(wbuf *w, const void *b, size_t len) { wb_write(w, b, len); }

/* -- the public map builder and accessors ------------------------------------------------ */

void rlb_msg_init(rlb_msg *m, void *buf, size_t cap) {
    m->buf = buf;
    m->cap = cap;
    m->len = 0;
    m->overflow = false;
}

#define MSGBUF(m) \
    wbuf w = {(m)->buf, (m)->cap, (m)->len, (m)->overflow}
#define MSGDONE(m) \
    (m)->len = w.len; \
    (m)->overflow = w.overflow

void rlb_msg_map(rlb_msg *m, uint32_t pairs) { MSGBUF(m); rlbi_wb_map(&w, pairs); MSGDONE(m); }
void rlb_msg_key(rlb_msg *m, const char *key) {
    MSGBUF(m);
    rlbi_wb_str(&w, key, strlen(key));
    MSGDONE(m);
}
void rlb_msg_f64(rlb_msg *m, double v) { MSGBUF(m); rlbi_wb_f64(&w, v); MSGDONE(m); }
void rlb_msg_i64(rlb_msg *m, int64_t v) { MSGBUF(m); rlbi_wb_i64(&w, v); MSGDONE(m); }
void rlb_msg_bool(rlb_msg *m, bool v) { MSGBUF(m); rlbi_wb_bool(&w, v); MSGDONE(m); }
void rlb_msg_str(rlb_msg *m, const char *s) {
    MSGBUF(m);
    rlbi_wb_str(&w, s, strlen(s));
    MSGDONE(m);
}

int rlb_msg_end(const rlb_msg *m) {
    if (m->overflow || m->len > INT32_MAX) return RLB_E_TOOBIG;
    return (int)m->len;
}

/* Moves the cursor to the value at a dotted path; RLB_OK or an error. */
static int find_path(mp_cur *c, const char *path) {
    while (*path) {
        const char *dot = strchr(path, '.');
        size_t klen = dot ? (size_t)(dot - path) : strlen(path);
        uint32_t pairs;
        if (!rlbi_mp_map(c, &pairs)) return RLB_E_TYPE;
        bool found = false;
        for (uint32_t i = 0; i < pairs && !found; i++) {
            const char *k = NULL;
            uint32_t kl = 0;
            if (!rlbi_mp_str(c, &k, &kl)) return RLB_E_TYPE;
            if (kl == klen && memcmp(k, path, klen) == 0) found = true;
            else if (!rlbi_mp_skip(c)) return RLB_E_TYPE;
        }
        if (!found) return RLB_E_NOVALUE;
        path = dot ? dot + 1 : path + klen;
    }
    return RLB_OK;
}

int rlb_msg_get_f64(const void *msg, size_t len, const char *path, double *v) {
    mp_cur c;
    rlbi_mp_init(&c, msg, len);
    int rc = find_path(&c, path);
    if (rc != RLB_OK) return rc;
    return rlbi_mp_f64(&c, v) ? RLB_OK : RLB_E_TYPE;
}

int rlb_msg_get_i64(const void *msg, size_t len, const char *path, int64_t *v) {
    mp_cur c;
    rlbi_mp_init(&c, msg, len);
    int rc = find_path(&c, path);
    if (rc != RLB_OK) return rc;
    return rlbi_mp_i64(&c, v) ? RLB_OK : RLB_E_TYPE;
}

int rlb_msg_get_bool(const void *msg, size_t len, const char *path, bool *v) {
    mp_cur c;
    rlbi_mp_init(&c, msg, len);
    int rc = find_path(&c, path);
    if (rc != RLB_OK) return rc;
    return rlbi_mp_bool(&c, v) ? RLB_OK : RLB_E_TYPE;
}
