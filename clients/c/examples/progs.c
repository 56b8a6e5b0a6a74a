#include "progs.h"

#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>

unsigned long positive_arg(const char *prog, const char *what, const char *s) {
    char *end;
    unsigned long v = strtoul(s, &end, 10);
    if (*end || v == 0) {
        fprintf(stderr, "%s: %s must be a positive integer, not %s\n", prog, what, s);
        exit(2);
    }
    return v;
}

bool start_rt_thread(const char *prog, pthread_t *t, void *(*fn)(void *), void *arg) {
    (void)mlockall(MCL_CURRENT | MCL_FUTURE); /* no page faults in the loop, where permitted */
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    struct sched_param sp = {.sched_priority = 80};
    pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&attr, SCHED_FIFO);
    pthread_attr_setschedparam(&attr, &sp);
    bool fifo = pthread_create(t, &attr, fn, arg) == 0;
    pthread_attr_destroy(&attr);
    if (!fifo && pthread_create(t, NULL, fn, arg) != 0) {
        fprintf(stderr, "%s: cannot start the loop thread\n", prog);
        exit(1);
    }
    return fifo;
}
