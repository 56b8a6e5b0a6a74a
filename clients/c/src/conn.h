/* The I/O side's session state, shared by its modules: stream.c (TCP frames and sealed
 * records), datagram.c (UDP), send.c (what we send), receive.c (what we receive) and
 * session.c (handshake, life, reconnect). Not installed. */
#ifndef RLB_CONN_H
#define RLB_CONN_H

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
    bool sealed;
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
    int64_t retry_at;
    uint32_t backoff_ms;
    bool closed;
    size_t rr; /* round-robin start among UDP channels */
    uint64_t conn_malformed;
};


/* stream.c */
void tcp_frame_begin(rlb_conn *k, wbuf *w);
bool tcp_frame_end(rlb_conn *k, const wbuf *w);
bool tcp_flush(rlb_conn *k);
bool tcp_flush_blocking(rlb_conn *k, int64_t deadline);
bool tcp_open_records(rlb_conn *k);
bool tcp_read(rlb_conn *k);
const uint8_t *tcp_next_frame(rlb_conn *k, size_t *len, bool *bad);

/* datagram.c */
size_t udp_body_at(const rlb_conn *k);
size_t udp_body_cap(const rlb_conn *k);
void udp_send(rlb_conn *k, size_t body_len);
void udp_send_as(rlb_conn *k, size_t body_len, uint64_t token, bool sealed);
bool udp_replay_ok(rlb_conn *k, uint64_t ctr);
void udp_datagram(rlb_client *c, uint8_t *d, size_t n);
void udp_read(rlb_client *c);

/* send.c */
bool send_tcp_heartbeat(rlb_conn *k, int64_t now);
void send_udp_heartbeat(rlb_conn *k, int64_t now);
void send_udp_round(rlb_client *c);
void send_tcp_round(rlb_client *c);
void send_credits(rlb_client *c);
bool send_topic_connect(rlb_conn *k, rlb_channel *ch);
void ctl_begin(rlb_conn *k, wbuf *w);
bool ctl_end(rlb_conn *k, const wbuf *w);

/* receive.c */
void conn_malformed(rlb_conn *k);
void conn_packet(rlb_client *c, const uint8_t *body, size_t len, bool in_bundle);

/* session.c */
void conn_lost(rlb_client *c, const char *why);
void conn_close_sockets(rlb_conn *k);
size_t conn_pending_bytes(const rlb_conn *k);
rlb_channel *conn_channel(rlb_client *c, uint64_t id);

/* handshake.c: blocking, within the deadline */
rlb_status handshake_tcp(rlb_client *c, int64_t deadline);
rlb_status handshake_udp(rlb_client *c, int64_t deadline);

#endif
