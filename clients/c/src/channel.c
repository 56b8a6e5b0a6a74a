/*
 * Channels: declaring them (the only allocation a channel makes) and the real-time side's
 * reads and writes, which touch nothing but the channel's preallocated ring or triple buffer
 * and relaxed/acquire/release atomics: no lock, no allocation, no system call.
 * clock_gettime(CLOCK_REALTIME) for a value's stamp is answered by the vDSO on Linux.
 */
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "internal.h"

/* -- ring ------------------------------------------------------------------------------- */

static rlb_slot *slot_at(uint8_t *mem, size_t stride, size_t i) {
    return (rlb_slot *)(void *)(mem + stride * i);
}

rlb_slot *rlbi_ring_reserve(rlb_ring *r) {
    size_t h = atomic_load_explicit(&r->head, memory_order_relaxed);
    size_t t = atomic_load_explicit(&r->tail, memory_order_acquire);
    if (h - t >= r->cap) return NULL;
    return slot_at(r->mem, r->stride, h % r->cap);
}

void rlbi_ring_commit(rlb_ring *r) {
    size_t h = atomic_load_explicit(&r->head, memory_order_relaxed);
    atomic_store_explicit(&r->head, h + 1, memory_order_release);
}

rlb_slot *rlbi_ring_peek(rlb_ring *r, size_t i) {
    size_t t = atomic_load_explicit(&r->tail, memory_order_relaxed);
    size_t h = atomic_load_explicit(&r->head, memory_order_acquire);
    if (h - t <= i) return NULL;
    return slot_at(r->mem, r->stride, (t + i) % r->cap);
}

void rlbi_ring_release(rlb_ring *r, size_t n) {
    size_t t = atomic_load_explicit(&r->tail, memory_order_relaxed);
    atomic_store_explicit(&r->tail, t + n, memory_order_release);
}

size_t rlbi_ring_count(const rlb_ring *r) {
    size_t t = atomic_load_explicit(&r->tail, memory_order_acquire);
    size_t h = atomic_load_explicit(&r->head, memory_order_acquire);
    return h - t;
}

/* -- triple buffer ---------------------------------------------------------------------- */

#define FRESH 4u

static rlb_slot *triple_back(rlb_triple *tb) { return slot_at(tb->mem, tb->stride, tb->back); }

static void triple_publish(rlb_triple *tb) {
    unsigned old = atomic_exchange_explicit(&tb->middle, tb->back | FRESH, memory_order_acq_rel);
    tb->back = old & 3u;
}

/* The newest slot if one arrived since the last take, else NULL. */
static rlb_slot *triple_take(rlb_triple *tb) {
    if (!(atomic_load_explicit(&tb->middle, memory_order_relaxed) & FRESH)) return NULL;
    unsigned old = atomic_exchange_explicit(&tb->middle, tb->front, memory_order_acq_rel);
    tb->front = old & 3u;
    return slot_at(tb->mem, tb->stride, tb->front);
}

/* -- declaring -------------------------------------------------------------------------- */

void rlb_channel_opts_init(rlb_channel_opts *o, const char *topic, const char *msg_type,
                           const char *field) {
    memset(o, 0, sizeof *o);
    o->topic = topic;
    o->msg_type = msg_type;
    o->field = field;
    o->transport = RLB_UDP;
    o->mode = RLB_LATEST;
    o->capacity = 64;
    o->value_bytes = 16;
    o->flow = -1;
    o->qos_depth = 10;
}

uint32_t rlb_array_bytes(uint32_t n) { return 5u + 9u * n; }

static size_t stride_of(uint32_t value_bytes) {
    size_t s = sizeof(rlb_slot) + value_bytes;
    return (s + 7u) & ~(size_t)7u;
}

static bool latest_sub(const rlb_channel_opts *o, int dir) {
    return dir == DIR_SUBSCRIBE && o->mode == RLB_LATEST;
}

static size_t storage_for(const rlb_channel_opts *o, int dir) {
    size_t slots = latest_sub(o, dir) ? 3u : o->capacity;
    return slots * stride_of(o->value_bytes);
}

size_t rlb_channel_storage(const rlb_channel_opts *o) {
    size_t pub = storage_for(o, DIR_PUBLISH), sub = storage_for(o, DIR_SUBSCRIBE);
    return pub > sub ? pub : sub;
}

static char *dup_str(const char *s) {
    if (s == NULL) return NULL;
    size_t n = strlen(s) + 1;
    char *d = malloc(n);
    if (d) memcpy(d, s, n);
    return d;
}

void rlbi_chan_free(rlb_channel *ch) {
    if (ch == NULL) return;
    free(ch->topic);
    free(ch->msg_type);
    free(ch->field);
    free(ch->cur);
    free(ch->hist);
    if (!ch->user_storage) free(ch->ring.mem ? ch->ring.mem : ch->triple.mem);
    free(ch);
}

static rlb_status declare(rlb_client *c, const rlb_channel_opts *o, int dir, rlb_channel **out) {
    if (c == NULL || o == NULL || out == NULL || o->topic == NULL || o->msg_type == NULL)
        return RLB_E_INVAL;
    if (o->topic[0] != '/' || strlen(o->topic) > 256 || o->msg_type[0] == '\0' ||
        strlen(o->msg_type) > 128 || (o->field && (o->field[0] == '\0' || strlen(o->field) > 128)))
        return RLB_E_INVAL;
    if (o->value_bytes < 1 || o->value_bytes > 65536 ||
        (o->mode != RLB_LATEST && o->mode != RLB_QUEUE) ||
        (o->transport != RLB_UDP && o->transport != RLB_TCP) || o->flow < -1 || o->flow > 1)
        return RLB_E_INVAL;
    if (!latest_sub(o, dir) && (o->capacity < 1 || o->capacity > (1u << 24))) return RLB_E_INVAL;
    bool every = dir == DIR_PUBLISH || o->mode == RLB_QUEUE;
    bool flow = o->flow == -1 ? (o->transport == RLB_TCP && every) : o->flow == 1;
    if (flow && (o->transport != RLB_TCP || !every)) return RLB_E_INVAL; /* protocol.md 10.5 */
    if (c->cfg.control == RLB_UDP && o->transport == RLB_TCP) return RLB_E_INVAL; /* 8.2 */
    if (o->redundancy > 16 || (o->redundancy && o->transport != RLB_UDP)) return RLB_E_INVAL;
    /* the repeated values and a new one must fit one sealed datagram (1400 bytes) */
    if (o->redundancy && (o->redundancy + 1u) * (9u + o->value_bytes) + 40u > 1340u)
        return RLB_E_INVAL;
    if (c->started || c->connected_once) return RLB_E_STATE;
    if (c->n_channels >= c->cfg.max_channels) return RLB_E_INVAL;
    size_t need = storage_for(o, dir);
    if (o->storage != NULL && o->storage_bytes < need) return RLB_E_INVAL;

    rlb_channel *ch = calloc(1, sizeof *ch);
    if (ch == NULL) return RLB_E_NOMEM;
    ch->client = c;
    ch->dir = dir;
    ch->transport = o->transport;
    ch->mode = dir == DIR_PUBLISH ? RLB_QUEUE : o->mode;
    ch->flow = flow;
    ch->qos_depth = o->qos_depth;
    ch->redundancy = o->redundancy;
    if (dir == DIR_PUBLISH && o->redundancy)
        ch->hist = malloc((size_t)o->redundancy * stride_of(o->value_bytes));
    ch->value_bytes = o->value_bytes;
    ch->topic = dup_str(o->topic);
    ch->msg_type = dup_str(o->msg_type);
    ch->field = dup_str(o->field);
    ch->cur = malloc(o->value_bytes);
    uint8_t *mem = o->storage;
    ch->user_storage = mem != NULL;
    if (mem == NULL) mem = calloc(1, need);
    if (latest_sub(o, dir)) {
        ch->triple.mem = mem;
        ch->triple.stride = stride_of(o->value_bytes);
        atomic_init(&ch->triple.middle, 1u);
        ch->triple.back = 0;
        ch->triple.front = 2;
    } else {
        ch->ring.mem = mem;
        ch->ring.cap = o->capacity;
        ch->ring.stride = stride_of(o->value_bytes);
        atomic_init(&ch->ring.head, 0);
        atomic_init(&ch->ring.tail, 0);
    }
    if (ch->topic == NULL || ch->msg_type == NULL || (o->field && ch->field == NULL) ||
        ch->cur == NULL || mem == NULL || (dir == DIR_PUBLISH && o->redundancy && !ch->hist)) {
        rlbi_chan_free(ch);
        return RLB_E_NOMEM;
    }
    ch->credit = UINT64_MAX;
    ch->id = c->n_channels + 1;
    c->channels[c->n_channels++] = ch;
    *out = ch;
    return RLB_OK;
}

rlb_status rlb_publish(rlb_client *c, const rlb_channel_opts *o, rlb_channel **out) {
    return declare(c, o, DIR_PUBLISH, out);
}

rlb_status rlb_subscribe(rlb_client *c, const rlb_channel_opts *o, rlb_channel **out) {
    return declare(c, o, DIR_SUBSCRIBE, out);
}

uint32_t rlb_channel_id(const rlb_channel *ch) { return ch->id; }

/* -- writes (real-time side) ------------------------------------------------------------ */

static rlb_slot *begin(rlb_channel *ch, wbuf *w) {
    if (ch->dir != DIR_PUBLISH) return NULL;
    rlb_slot *s = rlbi_ring_reserve(&ch->ring);
    if (s == NULL) {
        atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
        return NULL;
    }
    rlbi_wb_init(w, s->data, ch->value_bytes);
    return s;
}

static int finish(rlb_channel *ch, rlb_slot *s, const wbuf *w) {
    if (w->overflow) return RLB_E_TOOBIG;
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    s->stamp = (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
    s->len = (uint32_t)w->len;
    rlbi_ring_commit(&ch->ring);
    return RLB_OK;
}

#define WRITE_WITH(ch, encode) \
    do { \
        if ((ch) == NULL) return RLB_E_INVAL; \
        wbuf w; \
        rlb_slot *s = begin((ch), &w); \
        if (s == NULL) return (ch)->dir != DIR_PUBLISH ? RLB_E_INVAL : RLB_E_FULL; \
        encode; \
        return finish((ch), s, &w); \
    } while (0)

int rlb_write_f64(rlb_channel *ch, double v) { WRITE_WITH(ch, rlbi_wb_f64(&w, v)); }
int rlb_write_f32(rlb_channel *ch, float v) { WRITE_WITH(ch, rlbi_wb_f64(&w, (double)v)); }
int rlb_write_i64(rlb_channel *ch, int64_t v) { WRITE_WITH(ch, rlbi_wb_i64(&w, v)); }
int rlb_write_i32(rlb_channel *ch, int32_t v) { WRITE_WITH(ch, rlbi_wb_i64(&w, v)); }
int rlb_write_u64(rlb_channel *ch, uint64_t v) { WRITE_WITH(ch, rlbi_wb_u64(&w, v)); }
int rlb_write_bool(rlb_channel *ch, bool v) { WRITE_WITH(ch, rlbi_wb_bool(&w, v)); }
int rlb_write_str(rlb_channel *ch, const char *str) {
    if (str == NULL) return RLB_E_INVAL;
    WRITE_WITH(ch, rlbi_wb_str(&w, str, strlen(str)));
}
int rlb_write_f64_array(rlb_channel *ch, const double *v, size_t n) {
    if (v == NULL && n > 0) return RLB_E_INVAL;
    WRITE_WITH(ch, {
        rlbi_wb_array(&w, (uint32_t)n);
        for (size_t i = 0; i < n; i++) rlbi_wb_f64(&w, v[i]);
    });
}
int rlb_write_i64_array(rlb_channel *ch, const int64_t *v, size_t n) {
    if (v == NULL && n > 0) return RLB_E_INVAL;
    WRITE_WITH(ch, {
        rlbi_wb_array(&w, (uint32_t)n);
        for (size_t i = 0; i < n; i++) rlbi_wb_i64(&w, v[i]);
    });
}
int rlb_write_raw(rlb_channel *ch, const void *msgpack, size_t len) {
    if (msgpack == NULL) return RLB_E_INVAL;
    mp_cur c; /* exactly one well-formed value, or the server would refuse the packet */
    rlbi_mp_init(&c, msgpack, len);
    if (!rlbi_mp_skip(&c) || c.p != c.end) return RLB_E_INVAL;
    WRITE_WITH(ch, rlbi_wb_raw(&w, msgpack, len));
}

/* -- reads (real-time side) ------------------------------------------------------------- */

static void take(rlb_channel *ch, const rlb_slot *s) {
    memcpy(ch->cur, s->data, s->len);
    ch->cur_len = s->len;
    ch->cur_stamp = s->stamp;
    ch->has_cur = true;
}

/* 1 if a new value became current, 0 if not, RLB_E_NOVALUE if there never was one. */
static int advance(rlb_channel *ch) {
    if (ch == NULL || ch->dir != DIR_SUBSCRIBE) return RLB_E_INVAL;
    int fresh = 0;
    if (ch->mode == RLB_LATEST) {
        rlb_slot *s = triple_take(&ch->triple);
        if (s != NULL) {
            take(ch, s);
            fresh = 1;
        }
    } else {
        rlb_slot *s = rlbi_ring_peek(&ch->ring, 0);
        if (s != NULL) {
            take(ch, s);
            rlbi_ring_release(&ch->ring, 1);
            atomic_fetch_add_explicit(&ch->n_consumed, 1, memory_order_relaxed);
            fresh = 1;
        }
    }
    if (!ch->has_cur) return RLB_E_NOVALUE;
    return fresh;
}

int rlb_read_f64(rlb_channel *ch, double *v) {
    int rc = advance(ch);
    if (rc < 0) return rc;
    mp_cur c;
    rlbi_mp_init(&c, ch->cur, ch->cur_len);
    return rlbi_mp_f64(&c, v) ? rc : RLB_E_TYPE;
}

int rlb_read_i64(rlb_channel *ch, int64_t *v) {
    int rc = advance(ch);
    if (rc < 0) return rc;
    mp_cur c;
    rlbi_mp_init(&c, ch->cur, ch->cur_len);
    return rlbi_mp_i64(&c, v) ? rc : RLB_E_TYPE;
}

int rlb_read_bool(rlb_channel *ch, bool *v) {
    int rc = advance(ch);
    if (rc < 0) return rc;
    mp_cur c;
    rlbi_mp_init(&c, ch->cur, ch->cur_len);
    return rlbi_mp_bool(&c, v) ? rc : RLB_E_TYPE;
}

int rlb_read_f64_array(rlb_channel *ch, double *v, size_t cap, size_t *n) {
    int rc = advance(ch);
    if (rc < 0) return rc;
    mp_cur c;
    uint32_t len;
    rlbi_mp_init(&c, ch->cur, ch->cur_len);
    if (!rlbi_mp_array(&c, &len) || len > cap) return RLB_E_TYPE;
    for (uint32_t i = 0; i < len; i++)
        if (!rlbi_mp_f64(&c, &v[i])) return RLB_E_TYPE;
    if (n) *n = len;
    return rc;
}

int rlb_read_raw(rlb_channel *ch, void *buf, size_t cap, size_t *len) {
    int rc = advance(ch);
    if (rc < 0) return rc;
    if (ch->cur_len > cap) return RLB_E_TOOBIG;
    memcpy(buf, ch->cur, ch->cur_len);
    if (len) *len = ch->cur_len;
    return rc;
}

int64_t rlb_read_stamp(const rlb_channel *ch) { return ch->has_cur ? ch->cur_stamp : 0; }

/* -- the I/O side's delivery into a subscribe channel ------------------------------------ */

bool rlbi_chan_deliver(rlb_channel *ch, int64_t stamp, const uint8_t *value, size_t len) {
    if (len > ch->value_bytes) {
        atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
        return false;
    }
    rlb_slot *s;
    if (ch->mode == RLB_LATEST) {
        s = triple_back(&ch->triple);
    } else {
        s = rlbi_ring_reserve(&ch->ring);
        if (s == NULL) {
            atomic_fetch_add_explicit(&ch->n_dropped, 1, memory_order_relaxed);
            return false;
        }
    }
    memcpy(s->data, value, len);
    s->len = (uint32_t)len;
    s->stamp = stamp;
    if (ch->mode == RLB_LATEST) triple_publish(&ch->triple);
    else rlbi_ring_commit(&ch->ring);
    ch->pushed++;
    atomic_fetch_add_explicit(&ch->n_values, 1, memory_order_relaxed);
    return true;
}

/* -- counters --------------------------------------------------------------------------- */

void rlb_channel_stats_get(const rlb_channel *ch, rlb_channel_stats *o) {
    rlb_channel *m = (rlb_channel *)ch; /* atomics are read, never written */
    o->values = atomic_load_explicit(&m->n_values, memory_order_relaxed);
    o->lost = atomic_load_explicit(&m->n_lost, memory_order_relaxed) +
              atomic_load_explicit(&m->n_unconfirmed, memory_order_relaxed);
    o->duplicates = atomic_load_explicit(&m->n_duplicates, memory_order_relaxed);
    o->dropped = atomic_load_explicit(&m->n_dropped, memory_order_relaxed);
    o->server_received = atomic_load_explicit(&m->n_srv_received, memory_order_relaxed);
    o->errors = atomic_load_explicit(&m->n_errors, memory_order_relaxed);
    o->last_error = atomic_load_explicit(&m->last_error, memory_order_relaxed);
    o->pending = ch->dir == DIR_PUBLISH ? (uint32_t)rlbi_ring_count(&m->ring) : 0;
    o->bound = atomic_load_explicit(&m->bound, memory_order_relaxed);
}
