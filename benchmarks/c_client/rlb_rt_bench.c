/*
 * rlb_rt_bench: the C client's side of benchmarks/c_client_rt.py (issue 28, point 6).
 * Every mode prints one JSON object on stdout; times are microseconds unless named _ns.
 *
 *   jitter SECONDS [HOST PORT CHANNELS]
 *       A 1 kHz SCHED_FIFO loop (mlockall, clock_nanosleep TIMER_ABSTIME) records each
 *       period's wake-up lateness and its length's deviation from 1 ms; with HOST PORT
 *       CHANNELS it also writes one value to each of CHANNELS publish channels per period
 *       while the library's I/O thread streams them to the server (and times the writes).
 *   pub HOST PORT PREFIX CHANNELS COUNT RATE_HZ [PERIOD_US]
 *       The loop writes COUNT values to each channel, each value its CLOCK_REALTIME send time
 *       in seconds; prints the process's CPU time (all threads) per value sent. PERIOD_US:
 *       the I/O thread's period (rlb_config.period_us, default 1000).
 *   sub HOST PORT PREFIX CHANNELS COUNT TIMEOUT_S
 *       Subscribes (FIFO rings), says "ready" on stderr, reads until COUNT values per channel
 *       arrived or the timeout: one-way latency = read time - value, and CPU per value.
 *   rawpub HOST PORT CHANNELS COUNT RATE_HZ    the baseline: one sendto(2) per value, made
 *   rawfwd PORT DEST_PORT TOTAL TIMEOUT_S      in the loop; a forwarder standing in for the
 *   rawsub PORT TOTAL TIMEOUT_S                server; a receiver (latency, CPU per value).
 *
 * Every loop is bounded (COUNT, SECONDS or TIMEOUT_S).
 */
#include <arpa/inet.h>
#include <errno.h>
#include <netinet/in.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "progs.h"
#include "rlbridge.h"

#define MAX_CH 64

static double now_s(clockid_t clock) {
    struct timespec ts;
    clock_gettime(clock, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static double cpu_s(void) {
    struct rusage ru;
    getrusage(RUSAGE_SELF, &ru);
    return (double)ru.ru_utime.tv_sec + (double)ru.ru_utime.tv_usec * 1e-6 +
           (double)ru.ru_stime.tv_sec + (double)ru.ru_stime.tv_usec * 1e-6;
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* "name": {"n", "p50", "p90", "p99", "p999", "max"} of v (sorted in place). */
static void print_dist(const char *name, double *v, size_t n, bool last) {
    qsort(v, n, sizeof *v, cmp_double);
#define Q(q) (n ? v[(size_t)((double)(n - 1) * (q))] : 0.0)
    printf("\"%s\": {\"n\": %zu, \"p50\": %.3f, \"p90\": %.3f, \"p99\": %.3f, \"p999\": %.3f, "
           "\"max\": %.3f}%s", name, n, Q(0.5), Q(0.9), Q(0.99), Q(0.999), n ? v[n - 1] : 0.0,
           last ? "" : ", ");
#undef Q
}

static unsigned long arg_ul(const char *s, const char *what) {
    return positive_arg("rlb_rt_bench", what, s);
}

/* -- the client: declare, connect, start ------------------------------------------------- */

static rlb_client *client(const char *host, const char *port, const char *name,
                          const char *prefix, unsigned n, bool publish, unsigned capacity,
                          uint32_t period_us, rlb_channel **ch) {
    rlb_config cfg;
    rlb_config_init(&cfg);
    if (period_us) cfg.period_us = period_us;
    cfg.host = host;
    cfg.port = (uint16_t)arg_ul(port, "PORT");
    cfg.name = name;
    rlb_client *c;
    rlb_status rc = rlb_client_new(&cfg, &c);
    static char topics[MAX_CH][128];
    for (unsigned i = 0; rc == RLB_OK && i < n; i++) {
        snprintf(topics[i], sizeof topics[i], "%s%u", prefix, i);
        rlb_channel_opts o;
        rlb_channel_opts_init(&o, topics[i], "std_msgs/msg/Float64", "data");
        o.capacity = capacity;
        o.mode = RLB_QUEUE;
        rc = publish ? rlb_publish(c, &o, &ch[i]) : rlb_subscribe(c, &o, &ch[i]);
    }
    if (rc == RLB_OK) rc = rlb_connect(c);
    if (rc == RLB_OK) rc = rlb_start(c);
    if (rc != RLB_OK) {
        fprintf(stderr, "rlb_rt_bench: %s: %s\n", name, rlb_status_text(rc));
        exit(1);
    }
    return c;
}

/* -- jitter and pub: the periodic loop --------------------------------------------------- */

typedef struct loop {
    rlb_channel *ch[MAX_CH];
    unsigned n;
    unsigned long periods;
    long period_ns;
    bool stamp_values; /* pub: each value its send time; jitter: the period number */
    int raw_fd;        /* rawpub: sendto per value instead of the client */
    double *late_us, *dev_us, *write_ns;
    unsigned long full, written;
} loop;

static void *run(void *arg) {
    loop *l = arg;
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    int64_t prev = 0;
    for (unsigned long p = 0; p < l->periods; p++) {
        next.tv_nsec += l->period_ns;
        while (next.tv_nsec >= 1000000000) {
            next.tv_nsec -= 1000000000;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        int64_t woke = mono_ns();
        int64_t due = (int64_t)next.tv_sec * 1000000000 + next.tv_nsec;
        if (l->late_us) l->late_us[p] = (double)(woke - due) / 1e3;
        if (l->dev_us && p > 0) l->dev_us[p - 1] = (double)(woke - prev - l->period_ns) / 1e3;
        prev = woke;
        int64_t t0 = mono_ns();
        for (unsigned c = 0; c < l->n; c++) {
            double v = l->stamp_values ? now_s(CLOCK_REALTIME) : (double)p;
            if (l->raw_fd >= 0) {
                double msg[2] = {v, (double)c};
                if (send(l->raw_fd, msg, sizeof msg, 0) == (ssize_t)sizeof msg) l->written++;
            } else if (rlb_write_f64(l->ch[c], v) == RLB_OK) {
                l->written++;
            } else {
                l->full++;
            }
        }
        if (l->write_ns && l->n) l->write_ns[p] = (double)(mono_ns() - t0) / l->n;
    }
    return NULL;
}

static int mode_jitter(int argc, char **argv) {
    if (argc != 3 && argc != 6) return 2;
    static loop l;
    l.periods = arg_ul(argv[2], "SECONDS") * 1000;
    l.period_ns = 1000000;
    l.raw_fd = -1;
    rlb_client *c = NULL;
    if (argc == 6) {
        l.n = (unsigned)arg_ul(argv[5], "CHANNELS");
        if (l.n > MAX_CH) return 2;
        c = client(argv[3], argv[4], "rt-bench-jitter", "/jitter_", l.n, true, 1024, 0, l.ch);
    }
    l.late_us = calloc(l.periods, sizeof(double));
    l.dev_us = calloc(l.periods, sizeof(double));
    l.write_ns = calloc(l.periods, sizeof(double));
    if (!l.late_us || !l.dev_us || !l.write_ns) return 1;
    pthread_t t;
    bool fifo = start_rt_thread("rlb_rt_bench", &t, run, &l);
    pthread_join(t, NULL);
    unsigned long long sent = 0;
    if (c != NULL) {
        rlb_flush(c, 10000);
        for (unsigned i = 0; i < l.n; i++) {
            rlb_channel_stats st;
            rlb_channel_stats_get(l.ch[i], &st);
            sent += st.values;
        }
        rlb_close(c);
    }
    printf("{\"mode\": \"jitter\", \"fifo\": %s, \"channels\": %u, \"written\": %lu, "
           "\"sent\": %llu, \"ring_full\": %lu, ", fifo ? "true" : "false", l.n, l.written,
           sent, l.full);
    print_dist("late_us", l.late_us, l.periods, false);
    for (unsigned long i = 0; i + 1 < l.periods; i++)
        l.dev_us[i] = l.dev_us[i] < 0 ? -l.dev_us[i] : l.dev_us[i];
    print_dist("period_dev_us", l.dev_us, l.periods - 1, l.n == 0);
    if (l.n) print_dist("write_ns", l.write_ns, l.periods, true);
    printf("}\n");
    return 0;
}

static int mode_pub(int argc, char **argv, bool raw) {
    if (argc != (raw ? 7 : 8) && (raw || argc != 9)) return 2;
    static loop l;
    int a = raw ? 4 : 5;
    l.n = (unsigned)arg_ul(argv[a], "CHANNELS");
    l.periods = arg_ul(argv[a + 1], "COUNT");
    l.period_ns = (long)(1000000000UL / arg_ul(argv[a + 2], "RATE_HZ"));
    l.stamp_values = true;
    l.raw_fd = -1;
    if (l.n > MAX_CH) return 2;
    rlb_client *c = NULL;
    if (raw) {
        struct sockaddr_in to = {.sin_family = AF_INET,
                                 .sin_port = htons((uint16_t)arg_ul(argv[3], "PORT"))};
        inet_pton(AF_INET, argv[2], &to.sin_addr);
        l.raw_fd = socket(AF_INET, SOCK_DGRAM, 0);
        if (l.raw_fd < 0 || connect(l.raw_fd, (struct sockaddr *)&to, sizeof to) < 0) return 1;
    } else {
        uint32_t period_us = argc == 9 ? (uint32_t)arg_ul(argv[8], "PERIOD_US") : 0;
        c = client(argv[2], argv[3], "rt-bench-pub", argv[4], l.n, true, 1024, period_us, l.ch);
    }
    double cpu0 = cpu_s(), wall0 = now_s(CLOCK_MONOTONIC);
    pthread_t t;
    bool fifo = start_rt_thread("rlb_rt_bench", &t, run, &l);
    pthread_join(t, NULL);
    unsigned long long sent = l.written;
    if (c != NULL) {
        rlb_flush(c, 10000);
        sent = 0;
        for (unsigned i = 0; i < l.n; i++) {
            rlb_channel_stats st;
            rlb_channel_stats_get(l.ch[i], &st);
            sent += st.values;
        }
    }
    double cpu = cpu_s() - cpu0, wall = now_s(CLOCK_MONOTONIC) - wall0;
    printf("{\"mode\": \"%s\", \"fifo\": %s, \"sent\": %llu, \"ring_full\": %lu, "
           "\"cpu_s\": %.6f, \"wall_s\": %.3f, \"cpu_us_per_value\": %.3f}\n",
           raw ? "rawpub" : "pub", fifo ? "true" : "false", sent, l.full, cpu, wall,
           sent ? cpu / (double)sent * 1e6 : 0.0);
    fflush(stdout);
    if (c != NULL) rlb_close(c);
    return 0;
}

static int mode_sub(int argc, char **argv) {
    if (argc != 8) return 2;
    rlb_channel *ch[MAX_CH];
    unsigned n = (unsigned)arg_ul(argv[5], "CHANNELS");
    unsigned long count = arg_ul(argv[6], "COUNT");
    double timeout = atof(argv[7]);
    if (n > MAX_CH) return 2;
    rlb_client *c = client(argv[2], argv[3], "rt-bench-sub", argv[4], n, false, 4096, 0, ch);
    fprintf(stderr, "ready\n");
    size_t total = (size_t)n * count, got = 0;
    double *lat = calloc(total, sizeof(double));
    if (lat == NULL) return 1;
    double cpu0 = 0, end = now_s(CLOCK_MONOTONIC) + timeout;
    while (got < total && now_s(CLOCK_MONOTONIC) < end) {
        if (rlb_read_wait(ch[0], 20) < 0 && got == 0) continue;
        if (got == 0) cpu0 = cpu_s(); /* from the first value on */
        for (unsigned i = 0; i < n; i++) {
            double v;
            while (got < total && rlb_read_f64(ch[i], &v) == 1) lat[got++] = (now_s(CLOCK_REALTIME) - v) * 1e6;
        }
    }
    double cpu = cpu_s() - cpu0;
    printf("{\"mode\": \"sub\", \"received\": %zu, \"cpu_us_per_value\": %.3f, ", got,
           got ? cpu / (double)got * 1e6 : 0.0);
    print_dist("latency_us", lat, got, true);
    printf("}\n");
    fflush(stdout);
    rlb_close(c);
    return got == total ? 0 : 1;
}

static int udp_bound(unsigned long port) {
    int fd = socket(AF_INET, SOCK_DGRAM, 0);
    struct sockaddr_in at = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
    at.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    int big = 4 << 20;
    setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &big, sizeof big);
    if (fd < 0 || bind(fd, (struct sockaddr *)&at, sizeof at) < 0) {
        fprintf(stderr, "rlb_rt_bench: cannot bind UDP port %lu: %s\n", port, strerror(errno));
        exit(1);
    }
    struct timeval tv = {0, 100000};
    setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    return fd;
}

static int mode_rawfwd(int argc, char **argv) {
    if (argc != 6) return 2;
    int in = udp_bound(arg_ul(argv[2], "PORT"));
    struct sockaddr_in to = {.sin_family = AF_INET,
                             .sin_port = htons((uint16_t)arg_ul(argv[3], "DEST_PORT"))};
    to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    int out = socket(AF_INET, SOCK_DGRAM, 0);
    if (out < 0 || connect(out, (struct sockaddr *)&to, sizeof to) < 0) return 1;
    unsigned long total = arg_ul(argv[4], "TOTAL"), done = 0;
    double end = now_s(CLOCK_MONOTONIC) + atof(argv[5]);
    fprintf(stderr, "ready\n");
    double cpu0 = cpu_s();
    uint8_t buf[2048];
    while (done < total && now_s(CLOCK_MONOTONIC) < end) {
        ssize_t k = recv(in, buf, sizeof buf, 0);
        if (k > 0 && send(out, buf, (size_t)k, 0) == k) done++;
    }
    printf("{\"mode\": \"rawfwd\", \"forwarded\": %lu, \"cpu_us_per_value\": %.3f}\n", done,
           done ? (cpu_s() - cpu0) / (double)done * 1e6 : 0.0);
    return done == total ? 0 : 1;
}

static int mode_rawsub(int argc, char **argv) {
    if (argc != 5) return 2;
    int in = udp_bound(arg_ul(argv[2], "PORT"));
    size_t total = arg_ul(argv[3], "TOTAL"), got = 0;
    double end = now_s(CLOCK_MONOTONIC) + atof(argv[4]);
    double *lat = calloc(total, sizeof(double));
    if (lat == NULL) return 1;
    fprintf(stderr, "ready\n");
    double cpu0 = 0;
    while (got < total && now_s(CLOCK_MONOTONIC) < end) {
        double msg[2];
        if (recv(in, msg, sizeof msg, 0) != (ssize_t)sizeof msg) continue;
        if (got == 0) cpu0 = cpu_s();
        lat[got++] = (now_s(CLOCK_REALTIME) - msg[0]) * 1e6;
    }
    printf("{\"mode\": \"rawsub\", \"received\": %zu, \"cpu_us_per_value\": %.3f, ", got,
           got ? (cpu_s() - cpu0) / (double)got * 1e6 : 0.0);
    print_dist("latency_us", lat, got, true);
    printf("}\n");
    return got == total ? 0 : 1;
}

int main(int argc, char **argv) {
    int rc = 2;
    if (argc >= 2) {
        if (strcmp(argv[1], "jitter") == 0) rc = mode_jitter(argc, argv);
        else if (strcmp(argv[1], "pub") == 0) rc = mode_pub(argc, argv, false);
        else if (strcmp(argv[1], "rawpub") == 0) rc = mode_pub(argc, argv, true);
        else if (strcmp(argv[1], "sub") == 0) rc = mode_sub(argc, argv);
        else if (strcmp(argv[1], "rawfwd") == 0) rc = mode_rawfwd(argc, argv);
        else if (strcmp(argv[1], "rawsub") == 0) rc = mode_rawsub(argc, argv);
    }
    if (rc == 2)
        fprintf(stderr, "usage: rlb_rt_bench jitter SECONDS [HOST PORT CHANNELS] | pub HOST PORT "
                        "PREFIX CHANNELS COUNT RATE_HZ [PERIOD_US] | sub HOST PORT PREFIX CHANNELS COUNT "
                        "TIMEOUT_S | rawpub HOST PORT CHANNELS COUNT RATE_HZ | rawfwd PORT "
                        "DEST_PORT TOTAL TIMEOUT_S | rawsub PORT TOTAL TIMEOUT_S\n");
    return rc;
}
