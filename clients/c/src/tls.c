/*
 * TLS 1.3 on the TCP connection (protocol.md 16.4), through OpenSSL when the library was built
 * with it (RLB_WITH_TLS): the server verified against CA files (or the system's) and the host
 * name, or pinned by its certificate's SHA-256; an optional client certificate. The frames of
 * section 2 travel inside TLS; the stream functions below are what stream.c reads and writes
 * with, plain or TLS alike. Without OpenSSL, cfg.tls is refused at rlb_client_new.
 */
#include <errno.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>

#include "conn.h"

#ifdef RLB_WITH_TLS
#include <openssl/err.h>
#include <openssl/evp.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

bool rlb_has_tls(void) { return true; }

rlb_status rlbi_tls_setup(rlb_client *c) {
    if (!c->cfg.tls) return RLB_OK;
    SSL_CTX *ctx = SSL_CTX_new(TLS_client_method());
    if (ctx == NULL) return RLB_E_NOMEM;
    SSL_CTX_set_min_proto_version(ctx, TLS1_3_VERSION);
    SSL_CTX_set_mode(ctx, SSL_MODE_ENABLE_PARTIAL_WRITE | SSL_MODE_ACCEPT_MOVING_WRITE_BUFFER);
    bool ok = true;
    if (c->cfg.tls_fingerprint == NULL) { /* verify by CA; a pin replaces it */
        SSL_CTX_set_verify(ctx, SSL_VERIFY_PEER, NULL);
        ok = c->cfg.tls_ca_file ? SSL_CTX_load_verify_locations(ctx, c->cfg.tls_ca_file, NULL)
                                : SSL_CTX_set_default_verify_paths(ctx);
    }
    if (ok && c->cfg.tls_cert_file)
        ok = SSL_CTX_use_certificate_chain_file(ctx, c->cfg.tls_cert_file) == 1 &&
             SSL_CTX_use_PrivateKey_file(ctx, c->cfg.tls_key_file ? c->cfg.tls_key_file
                                                                 : c->cfg.tls_cert_file,
                                         SSL_FILETYPE_PEM) == 1;
    if (!ok) {
        SSL_CTX_free(ctx);
        return RLB_E_INVAL; /* a CA or certificate file that does not load */
    }
    c->conn->tls_ctx = ctx;
    return RLB_OK;
}

void rlbi_tls_free(rlb_client *c) {
    if (c->conn && c->conn->tls_ctx) SSL_CTX_free(c->conn->tls_ctx);
}

void rlbi_tls_close(rlb_conn *k) {
    if (k->ssl) SSL_free(k->ssl);
    k->ssl = NULL;
}

static bool pinned(SSL *ssl, const char *hex) {
#if OPENSSL_VERSION_NUMBER >= 0x30000000L
    X509 *cert = SSL_get1_peer_certificate(ssl);
#else
    X509 *cert = SSL_get_peer_certificate(ssl);
#endif
    if (cert == NULL) return false;
    unsigned char md[EVP_MAX_MD_SIZE];
    unsigned int n = 0;
    bool ok = X509_digest(cert, EVP_sha256(), md, &n) == 1 && n == 32;
    X509_free(cert);
    char got[65];
    for (unsigned i = 0; ok && i < 32; i++) snprintf(got + 2 * i, 3, "%02x", md[i]);
    for (unsigned i = 0; ok && i < 64; i++) {
        char want = hex[i];
        if (want >= 'A' && want <= 'F') want = (char)(want - 'A' + 'a');
        ok = want == got[i];
    }
    return ok && hex[64] == '\0';
}

static void failed(rlb_client *c, SSL *ssl, const char *what) {
    char text[256];
    long verify = SSL_get_verify_result(ssl);
    unsigned long err = ERR_peek_last_error();
    if (verify != X509_V_OK)
        snprintf(text, sizeof text, "TLS: the server certificate does not verify: %s",
                 X509_verify_cert_error_string(verify));
    else
        snprintf(text, sizeof text, "TLS: %s%s%s", what, err ? ": " : "",
                 err ? ERR_reason_error_string(err) : "");
    ERR_clear_error();
    rlb_emit(c, RLB_EV_DISCONNECT, 21, 0, text);
}

rlb_status rlbi_tls_connect(rlb_client *c, int64_t deadline) {
    rlb_conn *k = c->conn;
    SSL *ssl = SSL_new(k->tls_ctx);
    if (ssl == NULL) return RLB_E_NOMEM;
    k->tls_error[0] = '\0';
    k->ssl = ssl;
    SSL_set_fd(ssl, k->tcp);
    if (c->cfg.tls_fingerprint == NULL) { /* the name (or address) the certificate must carry */
        X509_VERIFY_PARAM *param = SSL_get0_param(ssl);
        if (X509_VERIFY_PARAM_set1_ip_asc(param, c->cfg.host) != 1) {
            SSL_set_tlsext_host_name(ssl, c->cfg.host);
            SSL_set1_host(ssl, c->cfg.host);
        }
    }
    for (;;) {
        int r = SSL_connect(ssl);
        if (r == 1) break;
        int e = SSL_get_error(ssl, r);
        int64_t left = (deadline - rlb_mono_ns()) / 1000000;
        if ((e != SSL_ERROR_WANT_READ && e != SSL_ERROR_WANT_WRITE) || left <= 0) {
            failed(c, ssl, left <= 0 ? "no answer to the handshake" : "handshake failed");
            return SSL_get_verify_result(ssl) != X509_V_OK ? RLB_E_AUTH : RLB_E_CONNECT;
        }
        struct pollfd p = {k->tcp, e == SSL_ERROR_WANT_READ ? POLLIN : POLLOUT, 0};
        poll(&p, 1, (int)left);
    }
    if (c->cfg.tls_fingerprint && !pinned(ssl, c->cfg.tls_fingerprint)) {
        rlb_emit(c, RLB_EV_DISCONNECT, 21, 0, "TLS: the server certificate is not the pinned one");
        return RLB_E_AUTH;
    }
    return RLB_OK;
}

static ssize_t tls_result(rlb_conn *k, int r, size_t done) {
    if (r == 1) return (ssize_t)done;
    int e = SSL_get_error(k->ssl, r);
    if (e == SSL_ERROR_WANT_READ || e == SSL_ERROR_WANT_WRITE) {
        errno = EAGAIN;
        return -1;
    }
    unsigned long err = ERR_peek_last_error(); /* e.g. the server's alert: no certificate */
    if (err && ERR_reason_error_string(err))
        snprintf(k->tls_error, sizeof k->tls_error, "%s", ERR_reason_error_string(err));
    ERR_clear_error();
    if (e == SSL_ERROR_ZERO_RETURN) return 0;
    errno = EPIPE;
    return -1;
}

ssize_t rlbi_stream_recv(rlb_conn *k, void *buf, size_t n) {
    if (k->ssl == NULL) return recv(k->tcp, buf, n, MSG_DONTWAIT);
    size_t got = 0;
    int r = SSL_read_ex(k->ssl, buf, n, &got); /* before reading got: argument order */
    return tls_result(k, r, got);
}

ssize_t rlbi_stream_send(rlb_conn *k, const void *buf, size_t n) {
    if (k->ssl == NULL) return send(k->tcp, buf, n, MSG_NOSIGNAL | MSG_DONTWAIT);
    size_t put = 0;
    int r = SSL_write_ex(k->ssl, buf, n, &put);
    return tls_result(k, r, put);
}

bool rlbi_tls_pending(const rlb_conn *k) { return k->ssl && SSL_pending(k->ssl) > 0; }

#else /* without OpenSSL */

bool rlb_has_tls(void) { return false; }
rlb_status rlbi_tls_setup(rlb_client *c) { return c->cfg.tls ? RLB_E_INVAL : RLB_OK; }
void rlbi_tls_free(rlb_client *c) { (void)c; }
void rlbi_tls_close(rlb_conn *k) { (void)k; }
rlb_status rlbi_tls_connect(rlb_client *c, int64_t deadline) {
    (void)c, (void)deadline;
    return RLB_E_INVAL;
}
ssize_t rlbi_stream_recv(rlb_conn *k, void *buf, size_t n) {
    return recv(k->tcp, buf, n, MSG_DONTWAIT);
}
ssize_t rlbi_stream_send(rlb_conn *k, const void *buf, size_t n) {
    return send(k->tcp, buf, n, MSG_NOSIGNAL | MSG_DONTWAIT);
}
bool rlbi_tls_pending(const rlb_conn *k) {
    (void)k;
    return false;
}

#endif
