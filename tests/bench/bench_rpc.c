/*
 * RPC latency and throughput of a running volfxd, from a C client that costs the server's
 * two cores as little as possible (one thread, poll over every connection). Not run by ctest.
 *
 *   bench_rpc --port P [--conns 64] [--seconds 5] [--runs 5] [--pipeline 200000]
 *
 * (a) pipelined: one connection, N small requests kept 256 deep in flight; requests per second.
 * (b) concurrent: C connections, each with one request in flight at a time, for S seconds;
 *     requests per second and the p50 / p99 latency over every request. Run twice: closed
 *     loop (each connection sends again as soon as it has its answer, which saturates the
 *     server, so latency is mostly queueing: C / throughput), and paced at --rate requests per
 *     second per connection (default 100), the load of 64 interactive clients.
 * The small request is scene.get of camera.fov_y. Medians over the runs are printed as a
 * markdown table.
 */
#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "bench_util.h"

static const char request[] =
    "{\"jsonrpc\":\"2.0\",\"method\":\"scene.get\",\"params\":{\"path\":\"camera.fov_y\"},"
    "\"id\":1}\n";

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + (double)ts.tv_nsec / 1e9;
}

static int dial(int port) {
  int fd = socket(AF_INET, SOCK_STREAM, 0);
  struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  int one = 1;
  setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  if (connect(fd, (struct sockaddr *)&a, sizeof a) != 0) {
    perror("bench_rpc: connect");
    exit(1);
  }
  return fd;
}

/* Counts '\n' in a buffer: every response is one line. */
static long count_lines(const char *b, ssize_t n) {
  long k = 0;
  for (ssize_t i = 0; i < n; i++)
    k += b[i] == '\n';
  return k;
}

static double pipelined(int port, long total) {
  int fd = dial(port);
  const size_t rl = sizeof request - 1;
  const long depth = 256;
  char *batch = malloc(rl * (size_t)depth);
  for (long i = 0; i < depth; i++)
    memcpy(batch + (size_t)i * rl, request, rl);
  char buf[1 << 16];
  long sent = 0, got = 0;
  double t0 = now_s();
  while (got < total) {
    /* Keep up to 'depth' requests in flight, topped up a batch at a time. */
    if (sent - got <= depth / 2 && sent < total) {
      long n = depth - (sent - got);
      if (n > total - sent)
        n = total - sent;
      size_t len = rl * (size_t)n, off = 0;
      while (off < len) {
        ssize_t w = write(fd, batch + off, len - off);
        if (w <= 0) {
          perror("bench_rpc: write");
          exit(1);
        }
        off += (size_t)w;
      }
      sent += n;
    }
    ssize_t r = read(fd, buf, sizeof buf);
    if (r <= 0) {
      perror("bench_rpc: read");
      exit(1);
    }
    got += count_lines(buf, r);
  }
  double dt = now_s() - t0;
  close(fd);
  free(batch);
  return (double)total / dt;
}

/* 'rate' > 0 paces each connection to that many requests per second; 0 is a closed loop. */
static void concurrent(int port, int nconn, double seconds, double rate, double *rps, double *p50,
                       double *p99) {
  int *fd = malloc(sizeof(int) * (size_t)nconn);
  double *sent_at = malloc(sizeof(double) * (size_t)nconn);
  struct pollfd *pfd = malloc(sizeof(struct pollfd) * (size_t)nconn);
  size_t cap = 1 << 20, n = 0;
  double *lat = malloc(sizeof(double) * cap);
  for (int i = 0; i < nconn; i++) {
    fd[i] = dial(port);
    pfd[i].fd = fd[i];
    pfd[i].events = POLLIN;
  }
  double t0 = now_s(), end = t0 + seconds;
  for (int i = 0; i < nconn; i++) {
    sent_at[i] = now_s();
    if (write(fd[i], request, sizeof request - 1) < 0)
      exit(1);
  }
  char buf[4096];
  double *due = calloc((size_t)nconn, sizeof(double)); /* Paced: when to send next; 0 idle. */
  while (now_s() < end) {
    if (rate > 0) {
      double t = now_s();
      for (int i = 0; i < nconn; i++)
        if (due[i] > 0 && t >= due[i]) {
          due[i] = 0;
          sent_at[i] = t;
          if (write(fd[i], request, sizeof request - 1) < 0)
            exit(1);
        }
    }
    if (poll(pfd, (nfds_t)nconn, rate > 0 ? 1 : 100) <= 0)
      continue;
    for (int i = 0; i < nconn; i++) {
      if (!(pfd[i].revents & POLLIN))
        continue;
      ssize_t r = read(fd[i], buf, sizeof buf);
      if (r <= 0) {
        fprintf(stderr, "bench_rpc: connection %d closed\n", i);
        exit(1);
      }
      /* One request in flight per connection, so one line is one response. */
      if (count_lines(buf, r) > 0) {
        double t = now_s();
        if (n == cap) {
          cap *= 2;
          lat = realloc(lat, sizeof(double) * cap);
        }
        lat[n++] = (t - sent_at[i]) * 1e3;
        if (rate > 0) {
          due[i] = sent_at[i] + 1.0 / rate;
          continue;
        }
        sent_at[i] = t;
        if (write(fd[i], request, sizeof request - 1) < 0)
          exit(1);
      }
    }
  }
  double dt = now_s() - t0;
  qsort(lat, n, sizeof(double), bench_cmp_double);
  *rps = (double)n / dt;
  *p50 = n ? lat[n / 2] : 0;
  *p99 = n ? lat[(size_t)((double)n * 0.99)] : 0;
  for (int i = 0; i < nconn; i++)
    close(fd[i]);
  free(fd);
  free(sent_at);
  free(pfd);
  free(lat);
  free(due);
}

int main(int argc, char **argv) {
  int port = 0, nconn = 64, runs = 5;
  double seconds = 5, rate = 100;
  long total = 200000;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!strcmp(argv[i], "--port"))
      port = atoi(argv[i + 1]);
    else if (!strcmp(argv[i], "--conns"))
      nconn = atoi(argv[i + 1]);
    else if (!strcmp(argv[i], "--seconds"))
      seconds = atof(argv[i + 1]);
    else if (!strcmp(argv[i], "--runs"))
      runs = atoi(argv[i + 1]);
    else if (!strcmp(argv[i], "--rate"))
      rate = atof(argv[i + 1]);
    else if (!strcmp(argv[i], "--pipeline"))
      total = atol(argv[i + 1]);
  }
  if (port <= 0 || runs < 1 || runs > 99 || nconn < 1) {
    fprintf(stderr, "usage: bench_rpc --port P [--conns 64] [--seconds 5] [--runs 5] "
                    "[--pipeline 200000] [--rate 100]\n");
    return 2;
  }
  double a[99], rps[99], p50[99], p99[99], prps[99], pp50[99], pp99[99];
  for (int r = 0; r < runs; r++) {
    a[r] = pipelined(port, total);
    concurrent(port, nconn, seconds, 0, &rps[r], &p50[r], &p99[r]);
    concurrent(port, nconn, seconds, rate, &prps[r], &pp50[r], &pp99[r]);
    fprintf(stderr,
            "run %d: pipelined %.0f req/s; %d conns closed loop %.0f req/s p50 %.3f p99 %.3f ms; "
            "paced %.0f req/s p50 %.3f p99 %.3f ms\n",
            r + 1, a[r], nconn, rps[r], p50[r], p99[r], prps[r], pp50[r], pp99[r]);
  }
  printf("| measure (median of %d runs) | volfx | target |\n| --- | ---: | ---: |\n", runs);
  printf("| pipelined small requests, 1 connection | %.0f req/s | >= 50,000 req/s |\n",
         bench_median(a, runs));
  printf("| %d connections, closed loop: throughput | %.0f req/s | |\n", nconn,
         bench_median(rps, runs));
  printf("| %d connections, closed loop: p50 / p99 latency | %.3f / %.3f ms | p99 <= 2 ms |\n",
         nconn, bench_median(p50, runs), bench_median(p99, runs));
  printf("| %d connections at %.0f req/s each: throughput | %.0f req/s | |\n", nconn, rate,
         bench_median(prps, runs));
  printf("| %d connections at %.0f req/s each: p50 / p99 latency | %.3f / %.3f ms | p99 <= 2 ms "
         "|\n",
         nconn, rate, bench_median(pp50, runs), bench_median(pp99, runs));
  return 0;
}
