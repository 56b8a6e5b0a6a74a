/* Every allocation the library makes can fail: each is made to fail in turn (the linker's
 * --wrap of malloc and calloc), and each failure is a returned RLB_E_NOMEM, never a crash
 * or a leak (the sanitizer build checks the leaks). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

#include <cmocka.h>

#include "rlbridge.h"

void *__real_malloc(size_t n);
void *__real_calloc(size_t n, size_t size);
void *__wrap_malloc(size_t n);
void *__wrap_calloc(size_t n, size_t size);

static long countdown = -1; /* the allocation that fails: 0 = the next one; -1 = none */
static long made;

static int fail_now(void) {
    made++;
    if (countdown < 0) return 0;
    return countdown-- == 0;
}

void *__wrap_malloc(size_t n) { return fail_now() ? NULL : __real_malloc(n); }
void *__wrap_calloc(size_t n, size_t size) { return fail_now() ? NULL : __real_calloc(n, size); }

/* Creates a client with a publish and two subscribe channels; the first error, or RLB_OK. */
static int build(rlb_client **out) {
    rlb_config cfg;
    rlb_config_init(&cfg);
    rlb_client *c;
    int rc = rlb_client_new(&cfg, &c);
    if (rc != RLB_OK) return rc;
    *out = c;
    rlb_channel_opts o;
    rlb_channel *ch;
    rlb_channel_opts_init(&o, "/x", "geometry_msgs/msg/Twist", NULL);
    o.value_bytes = 128;
    if ((rc = rlb_publish(c, &o, &ch)) != RLB_OK) return rc;
    o.mode = RLB_QUEUE;
    if ((rc = rlb_subscribe(c, &o, &ch)) != RLB_OK) return rc;
    o.mode = RLB_LATEST;
    o.field = "linear.x";
    return rlb_subscribe(c, &o, &ch);
}

static void every_failed_allocation_is_an_error(void **state) {
    (void)state;
    rlb_client *c = NULL;
    countdown = -1;
    made = 0;
    assert_int_equal(build(&c), RLB_OK); /* how many allocations the whole set-up makes */
    rlb_close(c);
    long total = made;
    assert_true(total > 5);
    for (long k = 0; k < total; k++) {
        c = NULL;
        countdown = k;
        int rc = build(&c);
        countdown = -1;
        assert_int_equal(rc, RLB_E_NOMEM);
        rlb_close(c); /* NULL when the client itself could not be made */
    }
}

int main(void) {
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(every_failed_allocation_is_an_error),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
