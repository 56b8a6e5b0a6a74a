/* What the examples, the proof programs (tests/rt_seccomp.c) and the benchmark program
 * (benchmarks/c_client/rlb_rt_bench.c) share: one copy of the real-time loop thread's set-up
 * (a fix to it reaches every figure and proof) and of a numeric argument's check. */
#ifndef RLB_EXAMPLES_PROGS_H
#define RLB_EXAMPLES_PROGS_H

#include <pthread.h>
#include <stdbool.h>

/* s as a positive integer; otherwise exits 2 with "PROG: WHAT must be a positive integer". */
unsigned long positive_arg(const char *prog, const char *what, const char *s);
/* Starts fn as the loop thread: SCHED_FIFO (priority 80) when permitted, else normal.
 * Locks memory first (mlockall) when permitted. Returns whether it got SCHED_FIFO; exits 1
 * with "PROG: cannot start the loop thread" if no thread starts at all. */
bool start_rt_thread(const char *prog, pthread_t *t, void *(*fn)(void *), void *arg);

#endif
