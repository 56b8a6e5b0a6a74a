/*
 * librlbridge: a C11 client of the rlbridge wire protocol (docs/protocol.md), for
 * hard-real-time control code. docs/c-client.md is the guide; this header is the reference.
 *
 * Two sides, two threads (or one loop):
 *
 *  - The real-time side: rlb_write_* and rlb_read_*, rlb_link_state, rlb_channel_stats.
 *    Wait-free: no lock, no allocation, no system call (values cross through single-producer
 *    single-consumer rings and triple buffers preallocated when the channel is declared).
 *    Call them from one thread per channel direction (the ring has one producer, one consumer).
 *
 *  - The I/O side: rlb_connect, rlb_start (a background I/O thread) or rlb_spin_once (for a
 *    single-threaded target), rlb_flush, rlb_read_wait, rlb_close. These make system calls,
 *    may block and must stay out of the real-time thread.
 *
 * Every function that can fail returns an rlb_status (negative) and never aborts; allocation
 * happens only in rlb_client_new and rlb_publish / rlb_subscribe, and a failed allocation is
 * RLB_E_NOMEM.
 */
#ifndef RLBRIDGE_H
#define RLBRIDGE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define RLB_PROTOCOL_VERSION 1
#define RLB_DEFAULT_PORT 7411
#define RLB_MAX_KEY 256

typedef struct rlb_client rlb_client;
typedef struct rlb_channel rlb_channel;

/** Results: >= 0 success (reads: 1 = a new value, 0 = the last value again), < 0 errors. */
typedef enum rlb_status {
    RLB_OK = 0,
    RLB_NEW = 1,
    RLB_E_INVAL = -1,     /* a bad argument (the function says which in docs/c-client.md) */
    RLB_E_NOMEM = -2,     /* an allocation at declare/creation time failed */
    RLB_E_STATE = -3,     /* not now: e.g. rlb_publish after rlb_connect */
    RLB_E_FULL = -4,      /* write: the channel's ring is full; the value is dropped, counted */
    RLB_E_NOVALUE = -5,   /* read: no value has arrived yet */
    RLB_E_TYPE = -6,      /* read: the value is not of the type asked for (or does not fit) */
    RLB_E_CONNECT = -7,   /* no TCP connection / no answer from the server */
    RLB_E_AUTH = -8,      /* key refused, or the server could not prove the key */
    RLB_E_REFUSED = -9,   /* the server refused the session or a binding (see the event) */
    RLB_E_TIMEOUT = -10,  /* a bounded wait ended */
    RLB_E_IO = -11,       /* a socket error */
    RLB_E_TOOBIG = -12,   /* a value larger than the channel's value_bytes */
    RLB_E_KEYFILE = -13,  /* the key file cannot be read or has no key for this name */
    RLB_E_CLOSED = -14    /* the client is closed (no reconnect) */
} rlb_status;

/** Link state as the I/O side sees it (protocol.md section 11), readable without a call. */
typedef enum rlb_link {
    RLB_LINK_CONNECTING = 0, /* before the first session, or reconnecting */
    RLB_LINK_CONNECTED = 1,  /* silence < 1.5 heartbeat periods */
    RLB_LINK_DEGRADED = 2,   /* silence up to the watchdog timeout */
    RLB_LINK_LOST = 3        /* the session ended; reconnecting with backoff */
} rlb_link;

typedef enum rlb_transport { RLB_UDP = 0, RLB_TCP = 1 } rlb_transport;

/** How an incoming channel hands values to the reader. */
typedef enum rlb_mode {
    RLB_LATEST = 0, /* non-blocking: the read returns the newest value and whether it is new */
    RLB_QUEUE = 1   /* every value in order (FIFO ring); read pops the oldest unread one */
} rlb_mode;

/** Events, delivered on the I/O side (the thread of rlb_start / rlb_spin_once). */
typedef enum rlb_event_kind {
    RLB_EV_LINK = 1,        /* link state changed: ev->link */
    RLB_EV_ERROR = 2,       /* the server's Error(code, reason, channel) */
    RLB_EV_TOPIC_ERROR = 3, /* a binding refused: TopicError(channel, code, reason) */
    RLB_EV_DISCONNECT = 4,  /* the server said goodbye (code, reason) */
    RLB_EV_CONNECTED = 5,   /* a session was opened (again) and every channel bound */
    RLB_EV_UNCONFIRMED = 6  /* rlb_close: the server did not confirm a publish channel's last
                               values (code: how many) within timeout_ms; added to its lost */
} rlb_event_kind;

typedef struct rlb_event {
    rlb_event_kind kind;
    rlb_link link;
    int code;             /* protocol.md 12.2 error code, 0 for none */
    uint32_t channel;     /* channel id, 0 when the event concerns no channel */
    const char *reason;   /* valid during the callback only */
} rlb_event;

typedef void (*rlb_event_fn)(void *ctx, const rlb_event *event);

typedef struct rlb_config {
    const char *host;             /* server address (name or numeric), default "127.0.0.1" */
    uint16_t port;                /* default 7411 */
    const char *name;             /* client name (key file lookup, logs), default "rlb-c" */
    rlb_transport control;        /* RLB_TCP (default): a TCP session, UDP channels beside it;
                                     RLB_UDP: a UDP-only session (protocol.md 8.2), for a
                                     server without TCP; its channels must be UDP ones */
    const uint8_t *psk;           /* pre-shared key (raw bytes) or NULL: plain session */
    size_t psk_len;
    bool tls;                     /* TLS 1.3 on the TCP connection (a --tls-cert server; needs
                                     a library built with OpenSSL, else RLB_E_INVAL) */
    const char *tls_ca_file;      /* PEM CAs to verify the server with; NULL: the system's */
    const char *tls_fingerprint;  /* or pin the server certificate: its SHA-256, 64 hex */
    const char *tls_cert_file;    /* a client certificate (mutual TLS), PEM, or NULL */
    const char *tls_key_file;     /* its key (NULL: in the certificate file) */
    uint32_t max_channels;        /* channels the client can declare, default 32 */
    uint32_t connect_timeout_ms;  /* handshake + bindings, default 3000 */
    uint32_t period_us;           /* I/O thread: how often it takes values from the rings
                                     (the real-time side never wakes it), default 1000 */
    bool reconnect;               /* reopen the session with backoff, default true */
    uint32_t backoff_initial_ms;  /* default 50, doubling */
    uint32_t backoff_max_ms;      /* default 2000 */
    size_t tcp_buffer;            /* bytes of each TCP buffer (send, receive), default 256 KiB */
    int io_priority;              /* SCHED_FIFO priority of the rlb_start thread, 0: inherit */
    rlb_event_fn on_event;        /* may be NULL */
    void *event_ctx;
} rlb_config;

/** Options of one channel; start from rlb_channel_opts_init. */
typedef struct rlb_channel_opts {
    const char *topic;         /* e.g. "/cmd" */
    const char *msg_type;      /* e.g. "std_msgs/msg/Float64" */
    const char *field;         /* e.g. "data", "linear.x"; NULL = whole messages (maps) */
    rlb_transport transport;   /* how the server sends this channel's values; default UDP */
    rlb_mode mode;             /* incoming channels only; default RLB_LATEST */
    uint32_t capacity;         /* values the ring holds (publish, RLB_QUEUE), default 64 */
    uint32_t value_bytes;      /* largest encoded value, default 16: any number or bool;
                                  strings: length + 5; arrays: rlb_array_bytes(n); whole
                                  messages: what they need. Larger values are refused
                                  (write: RLB_E_TOOBIG; received: dropped, counted) */
    int flow;                  /* credit flow control: -1 default (on for TCP every-value
                                  channels: publish, and RLB_QUEUE subscribe), 0 off, 1 on */
    uint16_t qos_depth;        /* middleware history depth, default 10 */
    uint8_t redundancy;        /* UDP, 0..16: each datagram repeats the channel's previous k
                                  values (protocol.md 10.3); publish: this client does it,
                                  subscribe: the server does; a lost datagram loses nothing */
    void *storage;             /* optional user buffer for the ring (see rlb_channel_storage) */
    size_t storage_bytes;
} rlb_channel_opts;

/** Per-channel counters, each read with one relaxed atomic load (no system call). */
typedef struct rlb_channel_stats {
    uint64_t values;          /* publish: values sent; subscribe: values delivered to the ring */
    uint64_t lost;            /* subscribe: sequence gaps (protocol.md 10.2); publish: the
                                 server's LossReport count of values lost on the first hop,
                                 plus those rlb_close could not get confirmed */
    uint64_t duplicates;      /* subscribe: duplicates and stale values dropped */
    uint64_t dropped;         /* ring full: values the writer (or the I/O side) could not queue */
    uint64_t server_received; /* publish: LossReport.received */
    uint64_t errors;          /* Error / TopicError packets the server sent for the channel */
    int last_error;           /* the last one's code (protocol.md 12.2), 0 for none */
    uint32_t pending;         /* publish: values written, not yet sent */
    bool bound;               /* the current session has bound the channel */
} rlb_channel_stats;

/* -- set-up (not real-time) ------------------------------------------------------------ */

void rlb_config_init(rlb_config *cfg);
void rlb_channel_opts_init(rlb_channel_opts *opts, const char *topic, const char *msg_type,
                           const char *field);
/** Encoded bytes of an array of n numbers (value_bytes for an array channel). */
uint32_t rlb_array_bytes(uint32_t n);
/** Bytes of user storage a channel with these options needs (opts->storage). */
size_t rlb_channel_storage(const rlb_channel_opts *opts);

/** Reads the key for `name` from a key file in the server's --psk-file format (its own
 *  line, else the default line). key must hold RLB_MAX_KEY bytes. */
rlb_status rlb_load_psk_file(const char *path, const char *name, uint8_t *key, size_t *key_len);

/** Allocates the client and its buffers; copies cfg (and the key). */
rlb_status rlb_client_new(const rlb_config *cfg, rlb_client **out);

/** Declare channels; before rlb_connect. Allocates the channel's ring (unless storage). */
rlb_status rlb_publish(rlb_client *c, const rlb_channel_opts *opts, rlb_channel **out);
rlb_status rlb_subscribe(rlb_client *c, const rlb_channel_opts *opts, rlb_channel **out);

/** Opens the session and binds every channel; blocks up to connect_timeout_ms. */
rlb_status rlb_connect(rlb_client *c);
/** Starts the I/O thread (rlb_spin_once in a loop, reconnects included). */
rlb_status rlb_start(rlb_client *c);
/** One round of I/O: receive (waiting up to timeout_ms), send the rings' values, heartbeats,
 *  watchdog, reconnect. For targets without a spare thread; never together with rlb_start. */
rlb_status rlb_spin_once(rlb_client *c, uint32_t timeout_ms);
/** Waits until every value written so far has been handed to the sockets (I/O side). */
rlb_status rlb_flush(rlb_client *c, uint32_t timeout_ms);
/** Blocks until the channel has a new value or timeout_ms passed: 1 new, RLB_E_TIMEOUT.
 *  Not for the real-time thread (it sleeps on a condition variable). */
int rlb_read_wait(rlb_channel *ch, uint32_t timeout_ms);
/** Stops the I/O thread, sends what the rings hold, says goodbye once the server has the
 *  last values (bounded by timeout_ms; see docs/c-client.md), closes and frees everything. */
void rlb_close(rlb_client *c);

/** Whether this library was built with TLS (OpenSSL); cfg.tls is refused otherwise. */
bool rlb_has_tls(void);
uint32_t rlb_channel_id(const rlb_channel *ch);
const char *rlb_status_text(int status);

/* -- real-time side: wait-free, no lock, no allocation, no system call ------------------- */

int rlb_write_f64(rlb_channel *ch, double v);
int rlb_write_f32(rlb_channel *ch, float v);
int rlb_write_i64(rlb_channel *ch, int64_t v);
int rlb_write_i32(rlb_channel *ch, int32_t v);
int rlb_write_u64(rlb_channel *ch, uint64_t v);
int rlb_write_bool(rlb_channel *ch, bool v);
int rlb_write_str(rlb_channel *ch, const char *s);
int rlb_write_f64_array(rlb_channel *ch, const double *v, size_t n);
int rlb_write_i64_array(rlb_channel *ch, const int64_t *v, size_t n);
/** Any value already encoded as MessagePack (a whole message's map, rlb_msg_*). */
int rlb_write_raw(rlb_channel *ch, const void *msgpack, size_t len);

/** 1: a new value, 0: the last value again (nothing new), RLB_E_NOVALUE: none yet,
 *  RLB_E_TYPE: the value is not of this type (it is consumed all the same). */
int rlb_read_f64(rlb_channel *ch, double *v);
int rlb_read_i64(rlb_channel *ch, int64_t *v);
int rlb_read_bool(rlb_channel *ch, bool *v);
int rlb_read_f64_array(rlb_channel *ch, double *v, size_t cap, size_t *n);
/** The value's MessagePack bytes (whole messages: a map for rlb_msg_get_*). */
int rlb_read_raw(rlb_channel *ch, void *buf, size_t cap, size_t *len);
/** Stamp (sender's CLOCK_REALTIME ns) of the value the last read returned. */
int64_t rlb_read_stamp(const rlb_channel *ch);

rlb_link rlb_link_state(const rlb_client *c);
/** Smoothed round-trip time to the server from the heartbeat echo (protocol.md 11), ns;
 *  -1 before the first sample. */
int64_t rlb_rtt_ns(const rlb_client *c);
/** Times a session was opened (1 after rlb_connect, +1 per reconnect). */
uint64_t rlb_sessions(const rlb_client *c);
void rlb_channel_stats_get(const rlb_channel *ch, rlb_channel_stats *out);

/* -- whole messages: a MessagePack map builder and accessors (no allocation) ------------- */

/** A writer into a caller's buffer; any overflow makes rlb_msg_end return RLB_E_TOOBIG. */
typedef struct rlb_msg {
    uint8_t *buf;
    size_t cap, len;
    bool overflow;
} rlb_msg;

void rlb_msg_init(rlb_msg *m, void *buf, size_t cap);
void rlb_msg_map(rlb_msg *m, uint32_t pairs);   /* then `pairs` times: key, value */
void rlb_msg_key(rlb_msg *m, const char *key);
void rlb_msg_f64(rlb_msg *m, double v);
void rlb_msg_i64(rlb_msg *m, int64_t v);
void rlb_msg_bool(rlb_msg *m, bool v);
void rlb_msg_str(rlb_msg *m, const char *s);
/** The encoded length, or RLB_E_TOOBIG. */
int rlb_msg_end(const rlb_msg *m);

/** Reads a field of a map by dotted path ("linear.x"): RLB_OK, RLB_E_NOVALUE (no such
 *  field), RLB_E_TYPE. Walks the bytes in place. */
int rlb_msg_get_f64(const void *msg, size_t len, const char *path, double *v);
int rlb_msg_get_i64(const void *msg, size_t len, const char *path, int64_t *v);
int rlb_msg_get_bool(const void *msg, size_t len, const char *path, bool *v);

#ifdef __cplusplus
}
#endif
#endif /* RLBRIDGE_H */
