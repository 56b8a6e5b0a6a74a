/*
 * Every failed allocation at creation and declare time is a returned error (issue 28,
 * point 7). Linked with -Wl,--wrap=malloc,--wrap=calloc,--wrap=realloc, so the library's own
 * calls (a static library, linked into this program) go through the wrappers below, which
 * fail the n-th allocation. For n = 0, 1, 2, ... the program creates a client and declares
 * channels of every kind (publish and subscribe, FIFO and latest, field-bound and whole
 * messages, with and without user storage) until no allocation fails any more: each step must
 * return RLB_E_NOMEM exactly when one of its allocations failed, leave the client usable (the
 * next declare after a failed one succeeds) and rlb_close must free what was allocated. Under
 * -DRLB_SANITIZE=ON LeakSanitizer checks that nothing leaks on any of these paths.
 * Exit 0 with one summary line.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "rlbridge.h"

void *__real_malloc(size_t n);
void *__real_calloc(size_t n, size_t size);
void *__real_realloc(void *p, size_t n);
void *__wrap_malloc(size_t n);
void *__wrap_calloc(size_t n, size_t size);
void *__wrap_realloc(void *p, size_t n);

static long countdown = -1; /* the allocation that fails: 0 the next one; -1 none */
static unsigned long failed, calls;

static bool fail_now(void) {
    calls++;
    if (countdown < 0) return false;
    if (countdown-- == 0) {
        failed++;
        return true;
    }
    return false;
}

void *__wrap_malloc(size_t n) { return fail_now() ? NULL : __real_malloc(n); }
void *__wrap_calloc(size_t n, size_t size) { return fail_now() ? NULL : __real_calloc(n, size); }
void *__wrap_realloc(void *p, size_t n) { return fail_now() ? NULL : __real_realloc(p, n); }

static void expect(bool ok, const char *what, long n) {
    if (!ok) {
        fprintf(stderr, "alloc_fail: %s (failing allocation %ld)\n", what, n);
        exit(1);
    }
}

#define N_DECL 5
static uint64_t user_storage[4096];

static rlb_status declare(rlb_client *c, int i) {
    rlb_channel_opts o;
    rlb_channel *ch;
    switch (i) {
    case 0:
        rlb_channel_opts_init(&o, "/p", "std_msgs/msg/Float64", "data");
        return rlb_publish(c, &o, &ch);
    case 1:
        rlb_channel_opts_init(&o, "/q", "std_msgs/msg/Float64", "data");
        o.mode = RLB_QUEUE;
        o.transport = RLB_TCP;
        return rlb_subscribe(c, &o, &ch);
    case 2:
        rlb_channel_opts_init(&o, "/l", "std_msgs/msg/Float64", "data");
        return rlb_subscribe(c, &o, &ch);
    case 3:
        rlb_channel_opts_init(&o, "/m", "geometry_msgs/msg/Twist", NULL);
        o.value_bytes = 512;
        return rlb_publish(c, &o, &ch);
    default:
        rlb_channel_opts_init(&o, "/u", "std_msgs/msg/Float64", "data");
        o.storage = user_storage;
        o.storage_bytes = sizeof user_storage;
        return rlb_publish(c, &o, &ch);
    }
}

int main(void) {
    rlb_config cfg;
    rlb_config_init(&cfg);
    cfg.name = "alloc-fail";
    unsigned long nomem = 0;
    long n = 0;
    for (;; n++) {
        countdown = n;
        failed = 0;
        rlb_client *c = NULL;
        rlb_status rc = rlb_client_new(&cfg, &c);
        expect(rc == RLB_OK || rc == RLB_E_NOMEM, "rlb_client_new: neither ok nor NOMEM", n);
        expect((rc == RLB_E_NOMEM) == (failed > 0), "rlb_client_new hid a failed allocation", n);
        if (rc != RLB_OK) {
            expect(c == NULL, "rlb_client_new failed but set the client", n);
            nomem++;
            continue;
        }
        int declared = 0;
        for (int i = 0; i < N_DECL; i++) {
            unsigned long before = failed;
            rc = declare(c, i);
            expect(rc == RLB_OK || rc == RLB_E_NOMEM, "declare: neither ok nor NOMEM", n);
            expect((rc == RLB_E_NOMEM) == (failed > before), "declare hid a failed allocation",
                   n);
            if (rc == RLB_E_NOMEM) nomem++;
            else declared++;
        }
        /* After a failed declare the client is whole: the same declaration now succeeds. */
        countdown = -1;
        if (declared < N_DECL) {
            rlb_channel_opts o;
            rlb_channel *ch;
            rlb_channel_opts_init(&o, "/again", "std_msgs/msg/Float64", "data");
            expect(rlb_publish(c, &o, &ch) == RLB_OK, "declare after a failed one", n);
        }
        rlb_close(c);
        if (failed == 0) break; /* the n-th allocation is past the last one: all covered */
    }
    printf("alloc_fail: failed each of the %ld allocations of rlb_client_new and %d declares "
           "in turn: %lu RLB_E_NOMEM returned, no crash\n", n, N_DECL, nomem);
    return nomem > 0 && n > 0 ? 0 : 1;
}
