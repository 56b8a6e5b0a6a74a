#include "common.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void parse_args(int argc, char **argv, const char *usage, args *a) {
    memset(a, 0, sizeof *a);
    a->channels = 1;
    int pos = 0, want = strstr(usage, "RATE_HZ") || strstr(usage, "TIMEOUT_S") ? 5 : 4;
    const char *p[5] = {0};
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--tcp") == 0 && strstr(usage, "--tcp")) {
            a->tcp = true;
        } else if (strcmp(argv[i], "--channels") == 0 && strstr(usage, "--channels") &&
                   i + 1 < argc) {
            char *end;
            unsigned long n = strtoul(argv[++i], &end, 10);
            if (*end || n < 1 || n > 256) {
                fprintf(stderr, "%s: --channels takes 1..256, not %s\n", argv[0], argv[i]);
                exit(2);
            }
            a->channels = (unsigned)n;
        } else if (strcmp(argv[i], "--redundancy") == 0 && strstr(usage, "--redundancy") &&
                   i + 1 < argc) {
            char *end;
            unsigned long k = strtoul(argv[++i], &end, 10);
            if (*end || k > 16) {
                fprintf(stderr, "%s: --redundancy takes 0..16, not %s\n", argv[0], argv[i]);
                exit(2);
            }
            a->redundancy = (unsigned)k;
        } else if (strcmp(argv[i], "--mixed") == 0 && strstr(usage, "--mixed")) {
            a->mixed = true;
        } else if (strcmp(argv[i], "--udp-only") == 0 && strstr(usage, "--udp-only")) {
            a->udp_only = true;
        } else if (strcmp(argv[i], "--spin") == 0 && strstr(usage, "--spin")) {
            a->spin = true;
        } else if (strcmp(argv[i], "--tls-ca") == 0 && strstr(usage, "--tls") && i + 1 < argc) {
            a->tls_ca = argv[++i];
        } else if (strcmp(argv[i], "--tls-fingerprint") == 0 && strstr(usage, "--tls") &&
                   i + 1 < argc) {
            a->tls_fingerprint = argv[++i];
        } else if (strcmp(argv[i], "--tls-cert") == 0 && strstr(usage, "--tls") && i + 1 < argc) {
            a->tls_cert = argv[++i];
        } else if (strcmp(argv[i], "--tls-key") == 0 && strstr(usage, "--tls") && i + 1 < argc) {
            a->tls_key = argv[++i];
        } else if (strcmp(argv[i], "--psk-file") == 0 && i + 1 < argc) {
            a->psk_file = argv[++i];
        } else if (argv[i][0] == '-' && argv[i][1] == '-') {
            fprintf(stderr, "%s: unknown option %s\nusage: %s %s\n", argv[0], argv[i], argv[0],
                    usage);
            exit(2);
        } else if (pos < want) {
            p[pos++] = argv[i];
        } else {
            pos++;
        }
    }
    char *end;
    if (pos != want) {
        fprintf(stderr, "usage: %s %s\n", argv[0], usage);
        exit(2);
    }
    a->host = p[0];
    unsigned long port = strtoul(p[1], &end, 10);
    if (*end || port == 0 || port > 65535) {
        fprintf(stderr, "%s: PORT must be 1..65535, not %s\n", argv[0], p[1]);
        exit(2);
    }
    a->port = (uint16_t)port;
    a->topic = p[2];
    a->count = positive_arg(argv[0], "COUNT", p[3]);
    if (want == 4) return;
    a->number = strtod(p[4], &end);
    if (*end || !(a->number > 0)) {
        fprintf(stderr, "%s: %s must be a positive number, not %s\n", argv[0],
                strstr(usage, "RATE_HZ") ? "RATE_HZ" : "TIMEOUT_S", p[4]);
        exit(2);
    }
}

void config_from(const args *a, const char *prog, const char *name, rlb_config *cfg,
                 uint8_t key[RLB_MAX_KEY]) {
    rlb_config_init(cfg);
    cfg->host = a->host;
    cfg->port = a->port;
    cfg->name = name;
    if (a->udp_only) cfg->control = RLB_UDP;
    cfg->tls = a->tls_ca || a->tls_fingerprint;
    cfg->tls_ca_file = a->tls_ca;
    cfg->tls_fingerprint = a->tls_fingerprint;
    cfg->tls_cert_file = a->tls_cert;
    cfg->tls_key_file = a->tls_key;
    if (a->redundancy && a->tcp) {
        fprintf(stderr, "%s: --redundancy is for UDP: not with --tcp\n", prog);
        exit(2);
    }
    if (a->mixed && (a->tcp || a->udp_only || a->channels < 2)) {
        fprintf(stderr, "%s: --mixed takes --channels N (N >= 2), not --tcp or --udp-only\n",
                prog);
        exit(2);
    }
    if (a->udp_only && a->tcp) {
        fprintf(stderr, "%s: --tcp needs a TCP session: not with --udp-only\n", prog);
        exit(2);
    }
    if (a->psk_file) {
        size_t len = 0;
        rlb_status rc = rlb_load_psk_file(a->psk_file, name, key, &len);
        if (rc != RLB_OK) {
            fprintf(stderr, "%s: no key for %s in %s (%s)\n", prog, name, a->psk_file,
                    rlb_status_text(rc));
            exit(1);
        }
        cfg->psk = key;
        cfg->psk_len = len;
    }
}

void setup_failed(const char *prog, const args *a, int status) {
    const char *why = "";
    if ((a->tls_ca || a->tls_fingerprint) && !rlb_has_tls())
        why = " (this librlbridge was built without TLS: install libssl-dev, build again)";
    else if (a->tls_ca || a->tls_fingerprint)
        why = " (a TLS CA, certificate or key file that does not load, or a bad fingerprint)";
    fprintf(stderr, "%s: cannot set up the client: %s%s\n", prog, rlb_status_text(status), why);
}
