/*
 * fuzz_decode [--random N] [--seed S] CORPUS_DIR...
 *
 * Hardening (issue 28, point 7): every file of the corpus directories (fuzz/corpus: the
 * Python harnesses' seeds), then N mutated and N random inputs, go through the client's
 * receive path, each input four ways:
 *
 *   - a plain TCP stream, written in chunks to a socketpair and read as the session does
 *     (framing, frames larger than the buffer, every packet type's decoder);
 *   - a sealed TCP stream (records opened under the corpus's stream key, 16.5);
 *   - one UDP datagram, plain and sealed (token check, AEAD, replay window), read by udp_read;
 *   - the bytes as one packet body, alone and as a bundle's part (conn_packet);
 *   - the server's side of a handshake (handshake_tcp: ConnectAck, ConnectError, AuthChallenge),
 *     as a plain and as a keyed client; the corpus and every 8th generated input also as the
 *     UDP-only handshake's datagrams (handshake_udp, bounded by a 1 ms deadline).
 *
 * The I/O side is the library's own code (its internal functions, src/conn.h, prefixed
 * rlbi_): tcp_read, tcp_next_frame and conn_packet as the session's receive step calls them,
 * udp_read, and conn_lost when the stream cannot go on. Subscribe channels are bound so that
 * values reach their rings, and the reader side then reads them (as numbers, arrays, raw
 * bytes and message fields). A malformed packet must be a count (conn->malformed, a dropped
 * datagram, a lost session), never a crash: under -DRLB_SANITIZE=ON AddressSanitizer and
 * UndefinedBehaviorSanitizer abort on the first invalid access, overflow or leak, and the
 * invariants below abort too. Exit 0 with one summary line on stdout.
 */
#include <dirent.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "conn.h"

#define FUZZ_MAX_INPUT 8192
#define N_CHANNELS 6

static const uint8_t KEY_B[32] = {0,  1,  2,  3,  4,  5,  6,  7,  8,  9,  10,
                                  11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21,
                                  22, 23, 24, 25, 26, 27, 28, 29, 30, 31};

typedef struct totals {
    unsigned long inputs, malformed, records, sealed_dgrams, sessions_lost, events, reads;
    unsigned long handshakes, handshakes_ok;
} totals;

static totals T;

static void on_event(void *ctx, const rlb_event *ev) {
    (void)ctx;
    T.events += strlen(ev->reason) > 0 || ev->code != 0 || ev->channel != 0 || ev->kind != 0;
}

static void check(bool ok, const char *what) {
    if (!ok) {
        fprintf(stderr, "fuzz_decode: invariant broken: %s (input %lu)\n", what, T.inputs);
        abort();
    }
}

static rlb_client *make_client(rlb_channel **ch, bool keyed) {
    rlb_config cfg;
    rlb_config_init(&cfg);
    if (keyed) {
        cfg.psk = KEY_B;
        cfg.psk_len = sizeof KEY_B;
    }
    cfg.name = "fuzz";
    cfg.tcp_buffer = 4096; /* small: frames larger than the buffer are skipped, not stored */
    cfg.max_channels = N_CHANNELS;
    cfg.on_event = on_event;
    rlb_client *c;
    check(rlb_client_new(&cfg, &c) == RLB_OK, "client");
    static const struct {
        int dir;
        rlb_transport tr;
        rlb_mode mode;
        const char *field;
        uint32_t bytes;
    } spec[N_CHANNELS] = {
        {DIR_SUBSCRIBE, RLB_UDP, RLB_LATEST, "data", 16},   /* 1 */
        {DIR_SUBSCRIBE, RLB_TCP, RLB_QUEUE, "data", 16},    /* 2: credit */
        {DIR_PUBLISH, RLB_UDP, RLB_QUEUE, "data", 16},      /* 3 */
        {DIR_PUBLISH, RLB_TCP, RLB_QUEUE, "data", 16},      /* 4: credit */
        {DIR_SUBSCRIBE, RLB_UDP, RLB_QUEUE, NULL, 256},     /* 5: whole messages */
        {DIR_SUBSCRIBE, RLB_UDP, RLB_LATEST, "data", 128},  /* 6: arrays */
    };
    for (int i = 0; i < N_CHANNELS; i++) {
        rlb_channel_opts o;
        rlb_channel_opts_init(&o, "/fuzz", "std_msgs/msg/Float64", spec[i].field);
        o.transport = spec[i].tr;
        o.mode = spec[i].mode;
        o.value_bytes = spec[i].bytes;
        o.capacity = 8;
        rlb_status rc = spec[i].dir == DIR_PUBLISH ? rlb_publish(c, &o, &ch[i])
                                                   : rlb_subscribe(c, &o, &ch[i]);
        check(rc == RLB_OK, "declare");
    }
    c->connected_once = true;
    return c;
}

static void set_nonblock(int fd) { (void)fcntl(fd, F_SETFL, fcntl(fd, F_GETFL, 0) | O_NONBLOCK); }

/* The session's receive step on its TCP socket (session.c's spin_io, without the poll). */
static void receive_tcp(rlb_client *c) {
    rlb_conn *k = c->conn;
    bool ok = rlbi_tcp_read(k);
    for (;;) {
        size_t len;
        bool bad;
        const uint8_t *f = rlbi_tcp_next_frame(k, &len, &bad);
        if (bad) ok = false;
        if (f == NULL || !k->up) break;
        rlbi_conn_packet(c, f, len, false);
    }
    if (!ok && k->up) rlbi_conn_lost(c, "connection closed");
}

/* A live session on socketpairs: every channel bound, the client's socket ends in k. */
static void session_up(rlb_client *c, int *peer_tcp, int *peer_udp, bool sealed) {
    rlb_conn *k = c->conn;
    int s[2], d[2];
    check(socketpair(AF_UNIX, SOCK_STREAM, 0, s) == 0, "socketpair");
    check(socketpair(AF_UNIX, SOCK_DGRAM, 0, d) == 0, "socketpair");
    set_nonblock(s[0]);
    set_nonblock(s[1]);
    k->tcp = s[0];
    k->udp = d[0];
    *peer_tcp = s[1];
    *peer_udp = d[1];
    k->out_len = k->wire_off = k->wire_len = k->in_off = k->in_len = k->rec_len = k->skip = 0;
    k->dgram_tx = k->rec_tx = k->rec_rx = k->replay_top = 0;
    memset(k->replay_bits, 0, sizeof k->replay_bits);
    k->token = 7; /* the corpus's datagrams carry token 7 */
    k->hb_ms = 200;
    k->timeout_ms = 600;
    k->up = true;
    k->closed = false;
    k->sealed = sealed;  /* datagrams */
    k->records = sealed; /* the TCP stream */
    memset(&k->keys, 0, sizeof k->keys);
    memcpy(k->keys.rs2c, KEY_B, 32);
    memcpy(k->keys.ks2c, KEY_B, 32);
    for (uint32_t i = 0; i < c->n_channels; i++) {
        rlb_channel *ch = c->channels[i];
        ch->bind = BIND_ACKED;
        ch->next_seq = 0;
        ch->has_highest = false;
        ch->credit = ch->flow ? 0 : UINT64_MAX;
    }
}

static void session_down(rlb_client *c, int peer_tcp, int peer_udp) {
    rlb_conn *k = c->conn;
    if (!k->up) T.sessions_lost++;
    T.records += k->rec_rx;         /* sealed records that opened */
    T.sealed_dgrams += k->replay_top > 0; /* a sealed datagram that opened */
    rlbi_conn_close_sockets(k); /* idempotent: a lost session closed them already */
    close(peer_tcp);
    close(peer_udp);
}

static void invariants(const rlb_client *c) {
    const rlb_conn *k = c->conn;
    check(k->in_off <= k->in_len && k->in_len <= k->cap, "TCP input buffer bounds");
    check(k->rec_len <= RECORD_MAX + 24 + 8, "record buffer bounds");
    check(rlbi_conn_pending_bytes(k) <= k->wire_cap, "output buffer bounds");
    for (uint32_t i = 0; i < c->n_channels; i++) {
        const rlb_channel *ch = c->channels[i];
        if (ch->mode == RLB_QUEUE) check(rlbi_ring_count(&ch->ring) <= ch->ring.cap, "ring bounds");
    }
}

/* The reader's side of everything that arrived: every read kind on every subscribe channel. */
static void drain(rlb_client *c) {
    for (uint32_t i = 0; i < c->n_channels; i++) {
        rlb_channel *ch = c->channels[i];
        if (ch->dir != DIR_SUBSCRIBE) continue;
        for (int n = 0; n < 16; n++) {
            uint8_t raw[256];
            size_t len = 0;
            double v, arr[16];
            int64_t iv;
            bool bv;
            int rc = rlb_read_raw(ch, raw, sizeof raw, &len);
            if (rc <= 0) break;
            T.reads++;
            check(len <= ch->value_bytes, "a value larger than its slot");
            (void)rlb_read_f64(ch, &v); /* the same value again, as each type */
            (void)rlb_read_i64(ch, &iv);
            (void)rlb_read_bool(ch, &bv);
            (void)rlb_read_f64_array(ch, arr, 16, &len);
            (void)rlb_msg_get_f64(raw, len, "linear.x", &v);
            (void)rlb_msg_get_i64(raw, len, "data", &iv);
            (void)rlb_msg_get_bool(raw, len, "a.b.c", &bv);
        }
    }
}

static void as_stream(rlb_client *c, const uint8_t *data, size_t len, bool sealed) {
    int pt, pu;
    session_up(c, &pt, &pu, sealed);
    size_t step = len ? (size_t)data[0] % 17 + 1 : 1;
    for (size_t at = 1; at < len && c->conn->up; at += step) {
        size_t n = len - at < step ? len - at : step;
        check(write(pt, data + at, n) == (ssize_t)n, "socketpair write");
        receive_tcp(c);
        invariants(c);
    }
    if (c->conn->up) receive_tcp(c);
    invariants(c);
    session_down(c, pt, pu);
}

static void as_datagram(rlb_client *c, const uint8_t *data, size_t len, bool sealed) {
    int pt, pu;
    session_up(c, &pt, &pu, sealed);
    if (len > 0) check(send(pu, data, len, 0) == (ssize_t)len, "datagram send");
    rlbi_udp_read(c);
    invariants(c);
    session_down(c, pt, pu);
}

static void as_body(rlb_client *c, const uint8_t *data, size_t len) {
    int pt, pu;
    session_up(c, &pt, &pu, false);
    rlbi_conn_packet(c, data, len, false);
    if (c->conn->up) rlbi_conn_packet(c, data, len, true);
    invariants(c);
    session_down(c, pt, pu);
}

/* The server's answers to our Hello: the bytes (after the mode byte) as the TCP stream, then
 * the end of the stream; or as one datagram during the UDP-only handshake. */
static void as_handshake(rlb_client *c, const uint8_t *data, size_t len, bool udp) {
    int pt, pu;
    session_up(c, &pt, &pu, false);
    rlb_conn *k = c->conn;
    k->up = false; /* a session opens only after its handshake */
    rlb_status rc;
    if (udp) {
        if (len > 0) check(send(pu, data, len, 0) == (ssize_t)len, "datagram send");
        rc = rlbi_handshake_udp(c, rlb_mono_ns() + 1000000);
    } else {
        if (len > 1) check(write(pt, data + 1, len - 1) == (ssize_t)(len - 1), "stream write");
        shutdown(pt, SHUT_WR);
        int64_t deadline = rlb_mono_ns() + 30 * (int64_t)1000000000;
        rc = rlbi_handshake_tcp(c, deadline);
        check(rlb_mono_ns() < deadline, "the TCP handshake ends with the stream, not at its "
                                        "deadline");
    }
    check(rc <= RLB_OK, "a handshake status");
    T.handshakes++;
    T.handshakes_ok += rc == RLB_OK;
    invariants(c);
    k->up = true; /* not a lost session: session_down counts those */
    session_down(c, pt, pu);
}

static void one_input(rlb_client *c, rlb_client *keyed, const uint8_t *data, size_t len,
                      bool udp_handshake) {
    uint64_t before = c->conn->malformed;
    T.inputs++;
    as_stream(c, data, len, false);
    as_stream(c, data, len, true);
    for (int skip = 0; skip <= 1 && (size_t)skip <= len; skip++) { /* with the mode byte, without */
        as_datagram(c, data + skip, len - (size_t)skip, false);
        as_datagram(c, data + skip, len - (size_t)skip, true);
        as_body(c, data + skip, len - (size_t)skip);
    }
    as_handshake(c, data, len, false);
    as_handshake(keyed, data, len, false);
    if (udp_handshake) {
        as_handshake(c, data + (len > 0), len - (len > 0), true);
        as_handshake(keyed, data + (len > 0), len - (len > 0), true);
    }
    drain(c);
    T.malformed += c->conn->malformed - before;
}

static uint64_t rng_state = 0x9e3779b97f4a7c15ULL;

static uint64_t rnd(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

/* A well-formed value packet with a random value (a number, a string or binary of up to 400
 * bytes, an array of numbers, a map) for a random channel, sequence and stamp, as a frame and
 * a datagram (with the token): values of every size reach the channels' slots. */
static size_t structured(uint8_t *buf, size_t cap) {
    static uint8_t body[2048], filler[512];
    wbuf w;
    rlbi_wb_init(&w, body, sizeof body);
    unsigned parts = rnd() % 3 == 0 ? (unsigned)(rnd() % 4) + 1 : 0;
    if (parts) { /* a bundle of values */
        rlbi_wb_array(&w, 2);
        rlbi_wb_u64(&w, 32);
        rlbi_wb_array(&w, parts);
    }
    for (unsigned p = 0; p < (parts ? parts : 1); p++) {
        bool batch = rnd() % 4 == 0;
        uint32_t n = batch ? (uint32_t)(rnd() % 5) : 1;
        rlbi_wb_array(&w, 5);
        rlbi_wb_u64(&w, batch ? 9 : 8);
        rlbi_wb_u64(&w, rnd() % (N_CHANNELS + 2));
        rlbi_wb_u64(&w, rnd() % 4 ? rnd() % 64 : rnd());
        if (batch) {
            rlbi_wb_array(&w, n);
            for (uint32_t i = 0; i < n; i++) rlbi_wb_i64(&w, (int64_t)rnd());
            rlbi_wb_array(&w, n);
        } else {
            rlbi_wb_i64(&w, (int64_t)rnd());
        }
        for (uint32_t i = 0; i < n; i++) {
            size_t len = rnd() % 400;
            for (size_t b = 0; b < len; b++) filler[b] = (uint8_t)rnd();
            switch (rnd() % 5) {
            case 0: rlbi_wb_f64(&w, (double)(int64_t)rnd()); break;
            case 1: rlbi_wb_str(&w, (const char *)filler, len); break;
            case 2: rlbi_wb_bin(&w, filler, len); break;
            case 3:
                rlbi_wb_array(&w, (uint32_t)(len % 40));
                for (size_t j = 0; j < len % 40; j++) rlbi_wb_f64(&w, (double)j);
                break;
            default:
                rlbi_wb_map(&w, 1);
                rlbi_wb_str(&w, "linear", 6);
                rlbi_wb_map(&w, 1);
                rlbi_wb_str(&w, "x", 1);
                rlbi_wb_f64(&w, 1.5);
            }
        }
    }
    if (w.overflow || w.len + 13 > cap) return 0;
    buf[0] = (uint8_t)rnd(); /* the chunking byte; then a frame header, or a datagram's */
    bool dgram = rnd() % 2;
    buf[1] = 'R', buf[2] = 'B', buf[3] = RLB_PROTOCOL_VERSION;
    if (dgram) {
        buf[4] = F_BUNDLES;
        for (int i = 0; i < 8; i++) buf[5 + i] = i == 7 ? 7 : 0; /* token 7 */
        memcpy(buf + 13, body, w.len);
        return 13 + w.len;
    }
    buf[4] = 0;
    buf[5] = (uint8_t)(w.len >> 24), buf[6] = (uint8_t)(w.len >> 16);
    buf[7] = (uint8_t)(w.len >> 8), buf[8] = (uint8_t)w.len;
    memcpy(buf + 9, body, w.len);
    return 9 + w.len;
}

static uint8_t corpus[1024][FUZZ_MAX_INPUT];
static size_t corpus_len[1024];
static size_t n_corpus;

static void load_dir(rlb_client *c, rlb_client *keyed, const char *dir) {
    DIR *d = opendir(dir);
    if (d == NULL) {
        fprintf(stderr, "fuzz_decode: cannot open %s\n", dir);
        exit(2);
    }
    struct dirent *e;
    char path[4096];
    while ((e = readdir(d)) != NULL) {
        if (e->d_name[0] == '.') continue;
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        FILE *f = fopen(path, "rb");
        if (f == NULL) continue;
        static uint8_t buf[1 << 20];
        size_t n = fread(buf, 1, sizeof buf, f);
        fclose(f);
        one_input(c, keyed, buf, n, true);
        if (n_corpus < 1024 && n <= FUZZ_MAX_INPUT) {
            memcpy(corpus[n_corpus], buf, n);
            corpus_len[n_corpus++] = n;
        }
    }
    closedir(d);
}

int main(int argc, char **argv) {
    unsigned long random_n = 2000;
    int first_dir = 1;
    for (; first_dir < argc && argv[first_dir][0] == '-'; first_dir += 2) {
        if (first_dir + 1 >= argc) break;
        if (strcmp(argv[first_dir], "--random") == 0)
            random_n = strtoul(argv[first_dir + 1], NULL, 10);
        else if (strcmp(argv[first_dir], "--seed") == 0)
            rng_state = strtoull(argv[first_dir + 1], NULL, 10) | 1;
        else break;
    }
    if (first_dir >= argc) {
        fprintf(stderr, "usage: %s [--random N] [--seed S] CORPUS_DIR...\n", argv[0]);
        return 2;
    }
    uint64_t seed = rng_state;
    rlb_channel *ch[N_CHANNELS];
    rlb_channel *kch[N_CHANNELS];
    rlb_client *c = make_client(ch, false), *keyed = make_client(kch, true);
    for (int i = first_dir; i < argc; i++) load_dir(c, keyed, argv[i]);
    unsigned long from_corpus = T.inputs;
    static uint8_t buf[FUZZ_MAX_INPUT];
    for (unsigned long i = 0; i < random_n; i++) {
        size_t len;
        if (i % 3 == 2) {
            len = structured(buf, sizeof buf);
        } else if (n_corpus > 0 && i % 3 == 0) { /* a corpus file mutated: flips, cuts */
            size_t j = rnd() % n_corpus;
            len = corpus_len[j];
            memcpy(buf, corpus[j], len);
            for (int m = 0, edits = (int)(rnd() % 8) + 1; m < edits && len > 0; m++) {
                switch (rnd() % 4) {
                case 0: buf[rnd() % len] ^= (uint8_t)(1u << (rnd() % 8)); break;
                case 1: buf[rnd() % len] = (uint8_t)rnd(); break;
                case 2: len = rnd() % (len + 1); break;
                default: { /* an interesting byte: msgpack lengths at their edges */
                    static const uint8_t edge[] = {0xc1, 0xdc, 0xdd, 0xde, 0xdf, 0xdb,
                                                   0xc6, 0xff, 0x00, 0x7f, 0x80, 0x9f};
                    buf[rnd() % len] = edge[rnd() % sizeof edge];
                }
                }
            }
        } else { /* random bytes, often behind a valid header so they reach the decoder */
            len = rnd() % 512;
            for (size_t b = 0; b < len; b++) buf[b] = (uint8_t)rnd();
            if (len >= 13 && rnd() % 2) {
                uint32_t body = (uint32_t)(len - 9);
                buf[1] = 'R', buf[2] = 'B', buf[3] = RLB_PROTOCOL_VERSION, buf[4] = 0;
                buf[5] = (uint8_t)(body >> 24), buf[6] = (uint8_t)(body >> 16);
                buf[7] = (uint8_t)(body >> 8), buf[8] = (uint8_t)body;
            }
        }
        one_input(c, keyed, buf, len, i % 8 == 0);
    }
    rlb_close(c);
    rlb_close(keyed);
    printf("fuzz_decode: %lu inputs (%lu from the corpus, %lu generated, seed %llu): "
           "%lu malformed packets counted, %lu sealed records and %lu sealed datagrams opened, "
           "%lu new values read, %lu sessions ended by bad input, %lu events, %lu handshakes "
           "(%lu accepted); no crash\n",
           T.inputs, from_corpus, T.inputs - from_corpus, (unsigned long long)seed,
           T.malformed, T.records, T.sealed_dgrams, T.reads, T.sessions_lost, T.events,
           T.handshakes, T.handshakes_ok);
    if (from_corpus == 0 || T.malformed == 0 || T.reads == 0 || T.records == 0 ||
        T.sealed_dgrams == 0 || T.handshakes_ok == 0) {
        fprintf(stderr, "fuzz_decode: the inputs never reached the decoder\n");
        return 1;
    }
    return 0;
}
