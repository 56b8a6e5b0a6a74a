/*
 * The client object: configuration, the key file, the I/O thread and the waits that the
 * non-real-time side may use (rlb_flush, rlb_read_wait).
 */
#include <ctype.h>
#include <errno.h>
#include <sched.h>
#include <sodium.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "internal.h"

int64_t rlb_mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

int64_t rlb_wall_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

void rlb_config_init(rlb_config *cfg) {
    memset(cfg, 0, sizeof *cfg);
    cfg->host = "127.0.0.1";
    cfg->port = RLB_DEFAULT_PORT;
    cfg->name = "rlb-c";
    cfg->control = RLB_TCP;
    cfg->max_channels = 32;
    cfg->connect_timeout_ms = 3000;
    cfg->period_us = 1000;
    cfg->reconnect = true;
    cfg->backoff_initial_ms = 50;
    cfg->backoff_max_ms = 2000;
    cfg->tcp_buffer = 256 * 1024;
}

const char *rlb_status_text(int s) {
    switch (s) {
    case RLB_OK: return "ok";
    case RLB_NEW: return "new value";
    case RLB_E_INVAL: return "invalid argument";
    case RLB_E_NOMEM: return "out of memory";
    case RLB_E_STATE: return "not allowed in this state";
    case RLB_E_FULL: return "ring full";
    case RLB_E_NOVALUE: return "no value yet";
    case RLB_E_TYPE: return "value of another type";
    case RLB_E_CONNECT: return "cannot connect to the server";
    case RLB_E_AUTH: return "authentication failed";
    case RLB_E_REFUSED: return "refused by the server";
    case RLB_E_TIMEOUT: return "timed out";
    case RLB_E_IO: return "socket error";
    case RLB_E_TOOBIG: return "value too large";
    case RLB_E_KEYFILE: return "no usable key in the key file";
    case RLB_E_CLOSED: return "client closed";
    default: return "unknown status";
    }
}

/* -- key file (the server's --psk-file format, docs/security.md) ------------------------- */

static int hexval(int ch) {
    if (ch >= '0' && ch <= '9') return ch - '0';
    ch = tolower(ch);
    if (ch >= 'a' && ch <= 'f') return ch - 'a' + 10;
    return -1;
}

static bool parse_hex(const char *s, size_t n, uint8_t *key, size_t *len) {
    if (n % 2 || n / 2 > RLB_MAX_KEY || n / 2 < 16) return false;
    for (size_t i = 0; i < n / 2; i++) {
        int hi = hexval(s[2 * i]), lo = hexval(s[2 * i + 1]);
        if (hi < 0 || lo < 0) return false;
        key[i] = (uint8_t)(hi << 4 | lo);
    }
    *len = n / 2;
    return true;
}

rlb_status rlb_load_psk_file(const char *path, const char *name, uint8_t *key, size_t *key_len) {
    if (path == NULL || name == NULL || key == NULL || key_len == NULL) return RLB_E_INVAL;
    FILE *f = fopen(path, "r");
    if (f == NULL) return RLB_E_KEYFILE;
    char line[2048];
    bool own = false, dflt = false, bad = false;
    uint8_t dkey[RLB_MAX_KEY];
    size_t dlen = 0;
    while (fgets(line, sizeof line, f) != NULL) {
        char *hash = strchr(line, '#');
        if (hash) *hash = '\0';
        char *words[2];
        size_t lens[2];
        int n = 0;
        for (char *p = line; *p;) { /* positional words: the ones without '=' */
            while (*p && isspace((unsigned char)*p)) p++;
            if (!*p) break;
            char *w = p;
            while (*p && !isspace((unsigned char)*p)) p++;
            if (memchr(w, '=', (size_t)(p - w)) != NULL) continue;
            if (n < 2) {
                words[n] = w;
                lens[n] = (size_t)(p - w);
            }
            n++;
        }
        if (n == 0) continue;
        if (n > 2) {
            bad = true;
            continue;
        }
        const char *who = n == 1 ? "*" : words[0];
        size_t who_len = n == 1 ? 1 : lens[0];
        const char *hex = words[n - 1];
        size_t hex_len = lens[n - 1];
        if (hex_len == 1 && hex[0] == '-') continue; /* an identity without a key */
        bool is_default = who_len == 1 && who[0] == '*';
        bool is_own = who_len == strlen(name) && memcmp(who, name, who_len) == 0;
        if (is_own && !own) {
            if (parse_hex(hex, hex_len, key, key_len)) own = true;
            else bad = true;
        } else if (is_default && !dflt) {
            if (parse_hex(hex, hex_len, dkey, &dlen)) dflt = true;
            else bad = true;
        }
    }
    fclose(f);
    if (own) return RLB_OK;
    if (dflt && !bad) {
        memcpy(key, dkey, dlen);
        *key_len = dlen;
        sodium_memzero(dkey, sizeof dkey);
        return RLB_OK;
    }
    return RLB_E_KEYFILE;
}

/* -- the client ------------------------------------------------------------------------ */

rlb_status rlb_client_new(const rlb_config *cfg, rlb_client **out) {
    if (cfg == NULL || out == NULL || cfg->max_channels == 0 || cfg->max_channels > 65536 ||
        cfg->period_us == 0 || cfg->tcp_buffer < 4096 || cfg->psk_len > RLB_MAX_KEY ||
        (cfg->psk_len > 0 && cfg->psk == NULL) || (cfg->name && strlen(cfg->name) > 128) ||
        (cfg->control != RLB_TCP && cfg->control != RLB_UDP) ||
        (cfg->tls && cfg->control == RLB_UDP) || /* TLS needs TCP (16.4) */
        (cfg->tls_fingerprint && strlen(cfg->tls_fingerprint) != 64))
        return RLB_E_INVAL;
    if (sodium_init() < 0) return RLB_E_NOMEM;
    rlb_client *c = calloc(1, sizeof *c);
    if (c == NULL) return RLB_E_NOMEM;
    c->cfg = *cfg;
    c->host = malloc(strlen(cfg->host ? cfg->host : "127.0.0.1") + 1);
    c->name = malloc(strlen(cfg->name ? cfg->name : "rlb-c") + 1);
    c->channels = calloc(cfg->max_channels, sizeof *c->channels);
    if (c->host == NULL || c->name == NULL || c->channels == NULL) {
        free(c->host);
        free(c->name);
        free(c->channels);
        free(c);
        return RLB_E_NOMEM;
    }
    strcpy(c->host, cfg->host ? cfg->host : "127.0.0.1");
    strcpy(c->name, cfg->name ? cfg->name : "rlb-c");
    c->cfg.host = c->host;
    c->cfg.name = c->name;
    if (cfg->psk_len) memcpy(c->psk, cfg->psk, cfg->psk_len);
    c->psk_len = cfg->psk_len;
    c->cfg.psk = NULL;
    if (cfg->tls_fingerprint) {
        for (int i = 0; i < 64; i++) c->fingerprint[i] = (char)tolower(cfg->tls_fingerprint[i]);
        c->cfg.tls_fingerprint = c->fingerprint;
    }
    atomic_init(&c->link, RLB_LINK_CONNECTING);
    atomic_init(&c->sessions, 0);
    atomic_init(&c->rtt_ns, -1);
    atomic_init(&c->stop, false);
    pthread_mutex_init(&c->wait_mu, NULL);
    pthread_condattr_t ca;
    pthread_condattr_init(&ca);
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    pthread_cond_init(&c->wait_cv, &ca);
    pthread_condattr_destroy(&ca);
    randombytes_buf(&c->rng, sizeof c->rng);
    c->rng |= 1;
    rlb_status rc = rlbi_conn_new(c);
    if (rc == RLB_OK && (rc = rlbi_tls_setup(c)) != RLB_OK) rlbi_conn_free(c);
    if (rc != RLB_OK) {
        pthread_mutex_destroy(&c->wait_mu);
        pthread_cond_destroy(&c->wait_cv);
        free(c->host);
        free(c->name);
        free(c->channels);
        free(c);
        return rc;
    }
    *out = c;
    return RLB_OK;
}

void rlb_emit(rlb_client *c, rlb_event_kind kind, int code, uint32_t channel,
              const char *reason) {
    if (c->cfg.on_event == NULL) return;
    rlb_event ev = {kind, (rlb_link)atomic_load(&c->link), code, channel, reason ? reason : ""};
    c->cfg.on_event(c->cfg.event_ctx, &ev);
}

void rlb_set_link(rlb_client *c, rlb_link link) {
    int old = atomic_exchange(&c->link, (int)link);
    if (old != (int)link) rlb_emit(c, RLB_EV_LINK, 0, 0, NULL);
}

rlb_link rlb_link_state(const rlb_client *c) {
    return (rlb_link)atomic_load_explicit(&((rlb_client *)c)->link, memory_order_relaxed);
}

int64_t rlb_rtt_ns(const rlb_client *c) {
    return atomic_load_explicit(&((rlb_client *)c)->rtt_ns, memory_order_relaxed);
}

uint64_t rlb_sessions(const rlb_client *c) {
    return atomic_load_explicit(&((rlb_client *)c)->sessions, memory_order_relaxed);
}

rlb_status rlb_connect(rlb_client *c) {
    if (c == NULL) return RLB_E_INVAL;
    if (c->started || c->connected_once) return RLB_E_STATE;
    rlb_status rc = rlbi_conn_open(c);
    if (rc == RLB_OK) c->connected_once = true;
    return rc;
}

/* One round of I/O, then a wake-up for rlb_read_wait / rlb_flush sleepers. */
static rlb_status spin(rlb_client *c, uint32_t timeout_ms) {
    rlb_status rc = rlbi_conn_spin(c, timeout_ms);
    pthread_mutex_lock(&c->wait_mu); /* wake rlb_read_wait / rlb_flush; no waiter: no syscall */
    pthread_cond_broadcast(&c->wait_cv);
    pthread_mutex_unlock(&c->wait_mu);
    return rc;
}

rlb_status rlb_spin_once(rlb_client *c, uint32_t timeout_ms) {
    if (c == NULL) return RLB_E_INVAL;
    if (!c->connected_once || c->started) return RLB_E_STATE; /* the I/O thread's job */
    return spin(c, timeout_ms);
}

static void *io_main(void *arg) {
    rlb_client *c = arg;
    uint32_t ms = c->cfg.period_us / 1000;
    while (!atomic_load(&c->stop)) {
        if (ms == 0) { /* sub-millisecond periods: poll without waiting, then sleep */
            spin(c, 0);
            struct timespec ts = {0, (long)c->cfg.period_us * 1000};
            nanosleep(&ts, NULL);
        } else if (spin(c, ms) == RLB_E_CLOSED) {
            break;
        }
    }
    return NULL;
}

rlb_status rlb_start(rlb_client *c) {
    if (c == NULL) return RLB_E_INVAL;
    if (!c->connected_once || c->started) return RLB_E_STATE;
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    if (c->cfg.io_priority > 0) {
        struct sched_param sp = {.sched_priority = c->cfg.io_priority};
        pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
        pthread_attr_setschedpolicy(&attr, SCHED_FIFO);
        pthread_attr_setschedparam(&attr, &sp);
    }
    int err = pthread_create(&c->thread, &attr, io_main, c);
    if (err == EPERM && c->cfg.io_priority > 0) { /* not permitted: run it unprioritised */
        pthread_attr_setinheritsched(&attr, PTHREAD_INHERIT_SCHED);
        err = pthread_create(&c->thread, &attr, io_main, c);
    }
    pthread_attr_destroy(&attr);
    if (err != 0) return err == ENOMEM || err == EAGAIN ? RLB_E_NOMEM : RLB_E_IO;
    c->started = true;
    return RLB_OK;
}

static void deadline_of(struct timespec *ts, uint32_t ms) {
    clock_gettime(CLOCK_MONOTONIC, ts);
    ts->tv_sec += ms / 1000;
    ts->tv_nsec += (long)(ms % 1000) * 1000000;
    if (ts->tv_nsec >= 1000000000) {
        ts->tv_sec++;
        ts->tv_nsec -= 1000000000;
    }
}

static size_t unsent(rlb_client *c) {
    size_t n = 0;
    for (uint32_t i = 0; i < c->n_channels; i++)
        if (c->channels[i]->dir == DIR_PUBLISH) n += rlbi_ring_count(&c->channels[i]->ring);
    return n + rlbi_conn_unsent(c);
}

rlb_status rlb_flush(rlb_client *c, uint32_t timeout_ms) {
    if (c == NULL) return RLB_E_INVAL;
    int64_t end = rlb_mono_ns() + (int64_t)timeout_ms * 1000000;
    while (unsent(c) > 0) {
        if (rlb_mono_ns() >= end) return RLB_E_TIMEOUT;
        if (!c->started) {
            if (!c->connected_once) return RLB_E_STATE;
            rlb_spin_once(c, 1);
            continue;
        }
        struct timespec ts;
        deadline_of(&ts, 5);
        pthread_mutex_lock(&c->wait_mu);
        pthread_cond_timedwait(&c->wait_cv, &c->wait_mu, &ts);
        pthread_mutex_unlock(&c->wait_mu);
    }
    return RLB_OK;
}

static bool has_new(rlb_channel *ch) {
    if (ch->mode == RLB_LATEST)
        return atomic_load_explicit(&ch->triple.middle, memory_order_acquire) & 4u;
    return rlbi_ring_count(&ch->ring) > 0;
}

int rlb_read_wait(rlb_channel *ch, uint32_t timeout_ms) {
    if (ch == NULL || ch->dir != DIR_SUBSCRIBE) return RLB_E_INVAL;
    rlb_client *c = ch->client;
    int64_t end = rlb_mono_ns() + (int64_t)timeout_ms * 1000000;
    while (!has_new(ch)) {
        int64_t left = end - rlb_mono_ns();
        if (left <= 0) return RLB_E_TIMEOUT;
        uint32_t ms = (uint32_t)((left + 999999) / 1000000);
        if (!c->started) {
            if (!c->connected_once) return RLB_E_STATE;
            rlb_spin_once(c, ms < 10 ? ms : 10);
            continue;
        }
        struct timespec ts;
        deadline_of(&ts, ms < 50 ? ms : 50);
        pthread_mutex_lock(&c->wait_mu);
        if (!has_new(ch)) pthread_cond_timedwait(&c->wait_cv, &c->wait_mu, &ts);
        pthread_mutex_unlock(&c->wait_mu);
    }
    return RLB_NEW;
}

void rlb_close(rlb_client *c) {
    if (c == NULL) return;
    atomic_store(&c->stop, true);
    if (c->started) pthread_join(c->thread, NULL);
    rlbi_conn_goodbye(c);
    rlbi_conn_free(c);
    for (uint32_t i = 0; i < c->n_channels; i++) rlbi_chan_free(c->channels[i]);
    free(c->channels);
    pthread_mutex_destroy(&c->wait_mu);
    pthread_cond_destroy(&c->wait_cv);
    sodium_memzero(c->psk, sizeof c->psk);
    free(c->host);
    free(c->name);
    free(c);
}
