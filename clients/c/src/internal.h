/* Internals shared by the library's modules; not installed. */
#ifndef RLB_INTERNAL_H
#define RLB_INTERNAL_H

#include <pthread.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "rlbridge.h"

/* -- MessagePack: a cursor decoder (no allocation) and an encoder into a fixed buffer ----- */

typedef struct mp_cur {
    const uint8_t *p, *end;
    bool err;
} mp_cur;

void rlbi_mp_init(mp_cur *c, const void *data, size_t len);
bool rlbi_mp_array(mp_cur *c, uint32_t *n);
bool rlbi_mp_map(mp_cur *c, uint32_t *n);
bool rlbi_mp_u64(mp_cur *c, uint64_t *v);
bool rlbi_mp_i64(mp_cur *c, int64_t *v);
bool rlbi_mp_f64(mp_cur *c, double *v); /* float32/64 and integers (widened) */
bool rlbi_mp_bool(mp_cur *c, bool *v);
bool rlbi_mp_nil(mp_cur *c);            /* consumes a nil if there is one */
bool rlbi_mp_str(mp_cur *c, const char **s, uint32_t *len);
bool rlbi_mp_bin(mp_cur *c, const uint8_t **b, uint32_t *len);
bool rlbi_mp_skip(mp_cur *c);           /* one whole value, iteratively (no recursion) */
bool rlbi_mp_is_int(const mp_cur *c);

typedef struct wbuf {
    uint8_t *buf;
    size_t cap, len;
    bool overflow;
} wbuf;

void rlbi_wb_init(wbuf *w, void *buf, size_t cap);
void rlbi_wb_array(wbuf *w, uint32_t n);
void rlbi_wb_map(wbuf *w, uint32_t n);
void rlbi_wb_u64(wbuf *w, uint64_t v);
void rlbi_wb_i64(wbuf *w, int64_t v);
void rlbi_wb_f64(wbuf *w, double v);
void rlbi_wb_bool(wbuf *w, bool v);
void rlbi_wb_nil(wbuf *w);
void rlbi_wb_str(wbuf *w, const char *s, size_t len);
void rlbi_wb_bin(wbuf *w, const uint8_t *b, size_t len);
void rlbi_wb_raw(wbuf *w, const void *b, size_t len);

/* -- crypto (section 16) ---------------------------------------------------------------- */

#define RLB_NONCE 16
typedef struct rlb_keys {
    uint8_t kc2s[32], ks2c[32], rc2s[32], rs2c[32];
} rlb_keys;

size_t rlb_transcript(const char *name, const uint8_t nc[16], const uint8_t ns[16],
                      uint8_t *out, size_t cap);
void rlb_proof(const uint8_t *key, size_t key_len, const char *label, const uint8_t *t,
               size_t t_len, uint8_t out[32]);
void rlb_derive(const uint8_t *key, size_t key_len, const uint8_t nc[16], const uint8_t ns[16],
                const uint8_t *t, size_t t_len, rlb_keys *keys);
/* 16.4: the datagram keys of a TLS session from ConnectAck.datagram_key and the token. */
void rlb_derive_tls(const uint8_t *secret, size_t len, uint64_t token, rlb_keys *keys);
/* AEAD with nonce 00000000 || counter (u64 BE); the tag is appended after the text. */
void rlb_seal(const uint8_t key[32], uint64_t counter, const uint8_t *aad, size_t aad_len,
              uint8_t *text, size_t len, uint8_t tag[16]);
bool rlb_open(const uint8_t key[32], uint64_t counter, const uint8_t *aad, size_t aad_len,
              uint8_t *text, size_t len, const uint8_t tag[16]);

/* -- rings: single producer, single consumer, fixed-size slots -------------------------- */

typedef struct rlb_slot {
    int64_t stamp;
    uint32_t len;
    uint32_t pad;
    uint8_t data[];
} rlb_slot;

typedef struct rlb_ring {
    _Atomic size_t head; /* written by the producer */
    char pad1[64 - sizeof(size_t)];
    _Atomic size_t tail; /* written by the consumer */
    char pad2[64 - sizeof(size_t)];
    size_t cap, stride;
    uint8_t *mem;
} rlb_ring;

rlb_slot *rlbi_ring_reserve(rlb_ring *r);   /* producer: NULL when full */
void rlbi_ring_commit(rlb_ring *r);
rlb_slot *rlbi_ring_peek(rlb_ring *r, size_t i); /* consumer: i-th unread slot or NULL */
void rlbi_ring_release(rlb_ring *r, size_t n);
size_t rlbi_ring_count(const rlb_ring *r);

/* Triple buffer: the newest value, wait-free both ways (one atomic exchange each). */
typedef struct rlb_triple {
    _Atomic unsigned middle; /* index | 4 when fresh */
    unsigned back, front;    /* owned by the writer / by the reader */
    size_t stride;
    uint8_t *mem;
} rlb_triple;

/* -- channels ------------------------------------------------------------------------- */

enum { DIR_PUBLISH = 0, DIR_SUBSCRIBE = 1 };
enum { BIND_NONE = 0, BIND_SENT = 1, BIND_ACKED = 2, BIND_REFUSED = 3 };

struct rlb_channel {
    rlb_client *client;
    uint32_t id;
    int dir;
    rlb_transport transport;
    rlb_mode mode;
    bool flow;
    uint16_t qos_depth;
    uint8_t redundancy;
    char *topic, *msg_type, *field; /* field NULL: whole messages */
    uint32_t value_bytes;
    bool user_storage;
    rlb_ring ring;     /* publish, and RLB_QUEUE subscribe */
    rlb_triple triple; /* RLB_LATEST subscribe */
    /* reader (real-time) side: the value the last read returned */
    uint8_t *cur;
    uint32_t cur_len;
    int64_t cur_stamp;
    bool has_cur;
    /* I/O side, per binding */
    int bind;
    uint64_t next_seq;     /* publish: number of the next value sent */
    uint64_t credit;       /* publish: send below this (UINT64_MAX: no limit) */
    uint64_t confirmed;    /* publish: LossReport.next_seq, values the server has (8.4) */
    bool has_highest;      /* subscribe: the rule of protocol.md 10.2 */
    uint64_t highest;
    uint64_t pushed;       /* subscribe: values pushed into the ring, ever */
    uint64_t credit_base;  /* subscribe+flow: credit = consumed - credit_base */
    uint64_t credit_sent;
    uint8_t *hist;          /* publish redundancy: the last values sent (I/O side) */
    uint32_t hist_n, hist_at; /* how many, and the slot of the oldest */
    /* counters, relaxed atomics */
    _Atomic uint64_t n_values, n_lost, n_duplicates, n_dropped, n_errors, n_srv_received;
    _Atomic uint64_t n_consumed; /* subscribe: values the reader took from the ring */
    _Atomic uint64_t n_unconfirmed; /* publish: lost at rlb_close, never confirmed (goodbye.c) */
    _Atomic int last_error;
    _Atomic bool bound;
};

/* -- the client ------------------------------------------------------------------------ */

typedef struct rlb_conn rlb_conn; /* session.c */

struct rlb_client {
    rlb_config cfg;
    char *host, *name;
    uint8_t psk[RLB_MAX_KEY];
    size_t psk_len;
    char fingerprint[65]; /* cfg.tls_fingerprint, lower-case hex, kept for every reconnect */
    rlb_channel **channels; /* by id - 1 */
    uint32_t n_channels;
    rlb_conn *conn;
    _Atomic int link;
    _Atomic uint64_t sessions;
    _Atomic int64_t rtt_ns; /* smoothed round trip, -1 before the first sample */
    _Atomic bool stop;
    bool started, connected_once;
    pthread_t thread;
    pthread_mutex_t wait_mu; /* rlb_read_wait / rlb_flush sleep on it; never the RT side */
    pthread_cond_t wait_cv;
    uint64_t rng;
};

int64_t rlb_mono_ns(void);
int64_t rlb_wall_ns(void);
void rlb_emit(rlb_client *c, rlb_event_kind kind, int code, uint32_t channel,
              const char *reason);
void rlb_set_link(rlb_client *c, rlb_link link);

/* channel.c: the I/O side's access to a subscribe channel's buffer */
bool rlbi_chan_deliver(rlb_channel *ch, int64_t stamp, const uint8_t *value, size_t len);
void rlbi_chan_free(rlb_channel *ch);

/* session.c */
rlb_status rlbi_conn_new(rlb_client *c);
void rlbi_conn_free(rlb_client *c);
rlb_status rlbi_conn_open(rlb_client *c);          /* handshake + bindings, blocking */
rlb_status rlbi_conn_spin(rlb_client *c, uint32_t timeout_ms);
size_t rlbi_conn_unsent(rlb_client *c);
void rlbi_conn_goodbye(rlb_client *c); /* goodbye.c */
/* tls.c: the TLS context of cfg.tls (RLB_E_INVAL when built without OpenSSL) */
rlb_status rlbi_tls_setup(rlb_client *c);
void rlbi_tls_free(rlb_client *c);

/* Test and fuzz entry points (session.c): received bytes without a socket. bind_all marks
 * every channel bound and sets the session token that datagrams must carry. */
void rlb_debug_bind_all(rlb_client *c, uint64_t token);
void rlb_debug_feed_datagram(rlb_client *c, const uint8_t *d, size_t n);
void rlb_debug_feed_stream(rlb_client *c, const uint8_t *bytes, size_t n);
uint64_t rlb_debug_malformed(const rlb_client *c);

#endif
