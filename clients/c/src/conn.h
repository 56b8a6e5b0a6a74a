/* The I/O side's session state, shared by its modules: stream.c (TCP frames and sealed
 * records), datagram.c (UDP), send.c (what we send), receive.c (what we receive) and
 * session.c (handshake, life, reconnect), goodbye.c (rlb_close's goodbye). Not installed. */
#ifndef RLB_CONN_H
#define RLB_CONN_H

#include <sys/types.h>

#include "internal.h"

enum {
    T_HELLO = 1, T_ACK = 2, T_CONNERR = 3, T_TOPIC = 4, T_TOPICACK = 5, T_TOPICERR = 6,
    T_VALUE = 8, T_BATCH = 9, T_HEARTBEAT = 10, T_DISCONNECT = 11, T_ERROR = 12, T_STATS = 13,
    T_CHALLENGE = 14, T_PROOF = 15, T_BUNDLE = 32, T_CREDIT = 34, T_LOSS = 35
};

#define F_SEALED 0x01
#define F_BUNDLES 0x80
#define UDP_HDR 12
#define SEAL_DGRAM 24
#define DGRAM_MAX 1400     /* what we send: below the path MTU (protocol.md section 3) */
#define RX_DGRAM 65536
#define RECORD_MAX 65536   /* plaintext bytes per sealed record (16.5) */
#define TCP_BATCH 1024     /* values per Batch frame we send (below max_batch) */
#define ROUND_DGRAMS 64    /* datagrams per send round, so that one spin stays bounded */

struct rlb_conn {
    int tcp, udp;
    bool up;
    uint64_t token;
    uint32_t hb_ms, timeout_ms;
    bool sealed;  /* datagrams sealed (a key, or TLS: 16.3, 16.4) */
    bool records; /* the TCP stream as sealed records (a key without TLS: 16.5) */
    void *tls_ctx, *ssl; /* OpenSSL's SSL_CTX and SSL (tls.c), NULL without TLS */
    char tls_error[128]; /* why TLS ended the connection (an alert from the server), or "" */
    rlb_keys keys;
    uint64_t dgram_tx, rec_tx, rec_rx;
    uint64_t replay_top, replay_bits[16]; /* 1024 counters below replay_top */
    size_t cap;                          /* of out / in */
    uint8_t *out, *wire, *in, *rec;
    size_t out_len, wire_off, wire_len, wire_cap, in_off, in_len, rec_len, skip;
    uint8_t *dg_tx, *dg_rx;
    int64_t last_rx, last_hb;
    bool tcp_data; /* values went over TCP this heartbeat period: no TCP heartbeat (sec. 11) */
    int64_t peer_sent, peer_rx, peer_wall, peer_wall_rx;
    int64_t srtt, rttvar; /* RFC 6298 smoothing of the heartbeat echo (protocol.md 11) */
    int64_t retry_at;
    uint32_t backoff_ms;
    bool closed;
    bool bye; /* rlb_close's goodbye runs: the session's end is no lost link (goodbye.c) */
    size_t rr; /* round-robin start among UDP channels */
    uint64_t malformed;
};


/* stream.c */
void rlbi_tcp_frame_begin(rlb_conn *k, wbuf *w);
bool rlbi_tcp_frame_end(rlb_conn *k, const wbuf *w);
bool rlbi_tcp_flush(rlb_conn *k);
bool rlbi_tcp_flush_blocking(rlb_conn *k, int64_t deadline);
bool rlbi_tcp_open_records(rlb_conn *k);
bool rlbi_tcp_read(rlb_conn *k);
const uint8_t *rlbi_tcp_next_frame(rlb_conn *k, size_t *len, bool *bad);

/* datagram.c */
size_t rlbi_udp_body_at(const rlb_conn *k);
size_t rlbi_udp_body_cap(const rlb_conn *k);
void rlbi_udp_send(rlb_conn *k, size_t body_len);
void rlbi_udp_send_as(rlb_conn *k, size_t body_len, uint64_t token, bool sealed);
bool rlbi_udp_replay_ok(rlb_conn *k, uint64_t ctr);
void rlbi_udp_datagram(rlb_client *c, uint8_t *d, size_t n);
void rlbi_udp_read(rlb_client *c);

/* send.c */
bool rlbi_send_tcp_heartbeat(rlb_conn *k, int64_t now);
void rlbi_send_udp_heartbeat(rlb_conn *k, int64_t now);
void rlbi_send_udp_round(rlb_client *c);
void rlbi_send_tcp_round(rlb_client *c);
void rlbi_send_credits(rlb_client *c);
bool rlbi_send_topic_connect(rlb_conn *k, rlb_channel *ch);
void rlbi_ctl_begin(rlb_conn *k, wbuf *w);
bool rlbi_ctl_end(rlb_conn *k, const wbuf *w);

/* receive.c */
void rlbi_conn_malformed(rlb_conn *k);
void rlbi_conn_packet(rlb_client *c, const uint8_t *body, size_t len, bool in_bundle);

/* session.c */
void rlbi_conn_lost(rlb_client *c, const char *why);
void rlbi_conn_close_sockets(rlb_conn *k);
size_t rlbi_conn_pending_bytes(const rlb_conn *k);
rlb_channel *rlbi_conn_channel(rlb_client *c, uint64_t id);

/* handshake.c: blocking, within the deadline */
rlb_status rlbi_handshake_tcp(rlb_client *c, int64_t deadline);
rlb_status rlbi_handshake_udp(rlb_client *c, int64_t deadline);

/* tls.c: TLS on the TCP connection, and the stream's reads and writes (plain or TLS) */
void rlbi_tls_close(rlb_conn *k);
rlb_status rlbi_tls_connect(rlb_client *c, int64_t deadline);
ssize_t rlbi_stream_recv(rlb_conn *k, void *buf, size_t n);
ssize_t rlbi_stream_send(rlb_conn *k, const void *buf, size_t n);
bool rlbi_tls_pending(const rlb_conn *k);

#endif
