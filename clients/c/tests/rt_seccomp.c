/*
 * rt_seccomp HOST PORT PREFIX CHANNELS COUNT RATE_HZ [--forbidden]
 *
 * The proof of the real-time rule (issue 28, point 6): a periodic loop thread writes the
 * values 0 .. COUNT-1 to CHANNELS publish channels PREFIX0 .. PREFIX<n-1> at RATE_HZ (the
 * even channels over UDP, the odd ones over TCP) while the library's I/O thread streams them
 * to the server. The same loop reads what the server sends back of PREFIX0 (a latest-value
 * subscription, UDP) and PREFIX1 (every value, a FIFO over TCP with credit), and calls the
 * other real-time functions (rlb_link_state, rlb_channel_stats_get, rlb_read_stamp). Before its first period the loop thread installs a seccomp filter on itself
 * alone (no TSYNC: the I/O thread and main are not filtered) that kills the whole process
 * (SIGSYS) on every system call but clock_nanosleep and clock_gettime. The loop therefore
 * runs to its end only if rlb_write_f64 makes no system call. After the last value the loop
 * thread parks in clock_nanosleep (its exit would be a call of its own), main flushes the
 * client and exits 0, which ends the parked thread with the process.
 *
 * --forbidden: the negative control, the same loop with one write(2) to stderr in its 10th
 * period; the process must die of SIGSYS, proving that the filter is installed and enforced.
 *
 * stderr: "filter installed" once the loop thread is filtered, then a summary line; with
 * "in order" when the FIFO subscription read every value 0 .. COUNT-1 in order.
 */
#include <errno.h>
#include <pthread.h>
#include <linux/audit.h>
#include <linux/filter.h>
#include <linux/seccomp.h>
#include <stdatomic.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "progs.h"
#include "rlbridge.h"

#if defined(__x86_64__)
#define RT_AUDIT_ARCH AUDIT_ARCH_X86_64
#elif defined(__aarch64__)
#define RT_AUDIT_ARCH AUDIT_ARCH_AARCH64
#elif defined(__arm__)
#define RT_AUDIT_ARCH AUDIT_ARCH_ARM
#elif defined(__i386__)
#define RT_AUDIT_ARCH AUDIT_ARCH_I386
#else
#error "rt_seccomp: add this architecture's AUDIT_ARCH_* value"
#endif

#define MAX_CHANNELS 64
#define ALLOW(nr) BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, (nr), 0, 1), \
                  BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW)

typedef struct loop {
    rlb_client *client;
    rlb_channel *ch[MAX_CHANNELS];
    rlb_channel *latest, *fifo; /* subscriptions to PREFIX0 and PREFIX1 */
    unsigned long latest_new, fifo_read, fifo_wrong;
    unsigned n;
    unsigned long count;
    long period_ns;
    bool forbidden;
    _Atomic int state; /* 0 starting, 1 filtered, 2 done, -1 the filter was refused */
    _Atomic bool go;   /* main has said "filter installed": the periods may begin */
    unsigned long full;
} loop;

/* Only this thread: seccomp(2) without SECCOMP_FILTER_FLAG_TSYNC filters the calling thread
 * (and threads it creates later: none). Killing the process, not the thread, makes a
 * forbidden call impossible to miss. */
static int install_filter(void) {
    struct sock_filter code[] = {
        BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(struct seccomp_data, arch)),
        BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, RT_AUDIT_ARCH, 1, 0),
        BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_KILL_PROCESS),
        BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(struct seccomp_data, nr)),
        ALLOW(__NR_clock_nanosleep),
        ALLOW(__NR_clock_gettime),
#ifdef __NR_clock_nanosleep_time64
        ALLOW(__NR_clock_nanosleep_time64),
#endif
#ifdef __NR_clock_gettime64
        ALLOW(__NR_clock_gettime64),
#endif
        BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_KILL_PROCESS),
    };
    struct sock_fprog prog = {(unsigned short)(sizeof code / sizeof code[0]), code};
    if (prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0) return -1;
    return prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, &prog, 0, 0);
}

static void *run(void *arg) {
    loop *l = arg;
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    if (install_filter() != 0) {
        atomic_store(&l->state, -1);
        return NULL;
    }
    atomic_store(&l->state, 1);
    /* From here on: clock_gettime, clock_nanosleep and the library's real-time side only. */
    while (!atomic_load(&l->go)) { /* main reports the filter first (a killed process can't) */
        struct timespec ms = {0, 1000000};
        clock_nanosleep(CLOCK_MONOTONIC, 0, &ms, NULL);
    }
    clock_gettime(CLOCK_MONOTONIC, &next);
    unsigned long next_value[MAX_CHANNELS] = {0}, done = 0;
    /* Bounded: a ring that stays full (an I/O side that stopped) ends the loop early, and the
     * values missing at the server say so. After the writes, up to 2 s more to read the FIFO's
     * last values as they come back. */
    unsigned long grace = 2 * (1000000000UL / (unsigned long)l->period_ns);
    for (unsigned long period = 0, after = 0;
         (done < l->n || (l->fifo_read < l->count && after++ < grace)) &&
         period < 4 * l->count + 1000 + grace;
         period++) {
        next.tv_nsec += l->period_ns;
        while (next.tv_nsec >= 1000000000) {
            next.tv_nsec -= 1000000000;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        if (l->forbidden && period == 10) {
            static const char msg[] = "rt_seccomp: a write(2) from the loop thread\n";
            (void)!write(2, msg, sizeof msg - 1); /* the filter kills the process here */
        }
        double v;
        if (rlb_read_f64(l->latest, &v) == 1) l->latest_new++;
        for (int k = 0; k < 64 && rlb_read_f64(l->fifo, &v) == 1; k++) /* every value, in order */
            l->fifo_wrong += v != (double)l->fifo_read++;
        l->fifo_wrong += rlb_read_stamp(l->fifo) < 0;
        rlb_channel_stats st;
        rlb_channel_stats_get(l->ch[0], &st);
        l->fifo_wrong += rlb_link_state(l->client) > RLB_LINK_LOST;
        for (unsigned c = 0; c < l->n; c++) {
            if (next_value[c] == l->count) continue;
            if (rlb_write_f64(l->ch[c], (double)next_value[c]) != RLB_OK) {
                l->full++; /* a full ring: the value waits a period */
            } else if (++next_value[c] == l->count) {
                done++;
            }
        }
    }
    atomic_store(&l->state, 2);
    for (;;) { /* parked: exiting the thread would make calls the filter forbids */
        struct timespec hour = {3600, 0};
        clock_nanosleep(CLOCK_MONOTONIC, 0, &hour, NULL);
    }
    return NULL;
}

static void wait_state(const loop *l, int at_least) {
    while (atomic_load(&l->state) >= 0 && atomic_load(&l->state) < at_least) {
        struct timespec ms = {0, 1000000};
        nanosleep(&ms, NULL);
    }
}

static unsigned long number(const char *s, const char *what) {
    return positive_arg("rt_seccomp", what, s);
}

int main(int argc, char **argv) {
    if (argc < 7 || argc > 8 || (argc == 8 && strcmp(argv[7], "--forbidden") != 0)) {
        fprintf(stderr, "usage: %s HOST PORT PREFIX CHANNELS COUNT RATE_HZ [--forbidden]\n",
                argv[0]);
        return 2;
    }
    static loop l;
    rlb_config cfg;
    rlb_config_init(&cfg);
    cfg.host = argv[1];
    cfg.port = (uint16_t)number(argv[2], "PORT");
    cfg.name = "rt_seccomp";
    l.n = (unsigned)number(argv[4], "CHANNELS");
    l.count = number(argv[5], "COUNT");
    l.period_ns = (long)(1000000000UL / number(argv[6], "RATE_HZ"));
    l.forbidden = argc == 8;
    if (l.n > MAX_CHANNELS || l.n < 2) {
        fprintf(stderr, "rt_seccomp: 2 to %d channels\n", MAX_CHANNELS);
        return 2;
    }
    rlb_client *c;
    rlb_status rc = rlb_client_new(&cfg, &c);
    char topics[MAX_CHANNELS][300];
    for (unsigned i = 0; rc == RLB_OK && i < l.n; i++) {
        snprintf(topics[i], sizeof topics[i], "%s%u", argv[3], i);
        rlb_channel_opts o;
        rlb_channel_opts_init(&o, topics[i], "std_msgs/msg/Float64", "data");
        o.transport = i % 2 ? RLB_TCP : RLB_UDP;
        o.capacity = 1024;
        rc = rlb_publish(c, &o, &l.ch[i]);
    }
    rlb_channel_opts o;
    rlb_channel_opts_init(&o, topics[0], "std_msgs/msg/Float64", "data");
    if (rc == RLB_OK) rc = rlb_subscribe(c, &o, &l.latest);
    rlb_channel_opts_init(&o, topics[1], "std_msgs/msg/Float64", "data");
    o.transport = RLB_TCP;
    o.mode = RLB_QUEUE;
    o.capacity = 4096;
    if (rc == RLB_OK) rc = rlb_subscribe(c, &o, &l.fifo);
    l.client = c;
    if (rc == RLB_OK) rc = rlb_connect(c);
    if (rc == RLB_OK) rc = rlb_start(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rt_seccomp: cannot set up the client: %s\n", rlb_status_text(rc));
        return 1;
    }
    pthread_t t;
    bool fifo = start_rt_thread("rt_seccomp", &t, run, &l);
    wait_state(&l, 1);
    if (atomic_load(&l.state) < 0) {
        fprintf(stderr, "rt_seccomp: the kernel refused the seccomp filter: %s\n",
                strerror(errno));
        return 1;
    }
    fprintf(stderr, "rt_seccomp: filter installed on the loop thread (%s)\n",
            fifo ? "SCHED_FIFO" : "SCHED_OTHER");
    atomic_store(&l.go, true);
    wait_state(&l, 2);
    rc = rlb_flush(c, 30000);
    unsigned long long sent = 0;
    for (unsigned i = 0; i < l.n; i++) {
        rlb_channel_stats st;
        rlb_channel_stats_get(l.ch[i], &st);
        sent += st.values;
    }
    fprintf(stderr, "rt_seccomp: loop done, %lu values x %u channels written, %llu sent, "
            "ring full %lu times; read back %lu new latest values, %lu FIFO values%s\n",
            l.count, l.n, sent, l.full, l.latest_new, l.fifo_read,
            l.fifo_read == l.count && l.fifo_wrong == 0 ? " in order" : "");
    rlb_close(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rt_seccomp: not everything was sent: %s\n", rlb_status_text(rc));
        return 1;
    }
    return 0; /* exit_group: ends the parked loop thread too */
}
