/* sd_notify messages to the service manager; see service.h. */
#include "service.h"

#include <stdarg.h>
#include <stdio.h>
#include <time.h>

#ifdef VOLFX_HAVE_SYSTEMD
#include <systemd/sd-daemon.h>
#endif

/* Sends 'state' (newline-separated assignments). The environment is kept (unset_environment
 * 0) so that every later message finds NOTIFY_SOCKET too. */
static void notify(const char *state) {
#ifdef VOLFX_HAVE_SYSTEMD
  sd_notify(0, state);
#else
  (void)state;
#endif
}

void service_status(const char *fmt, ...) {
  char msg[512];
  int n = snprintf(msg, sizeof msg, "STATUS=");
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(msg + n, sizeof msg - (size_t)n, fmt, ap);
  va_end(ap);
  notify(msg);
}

void service_ready(const char *status) {
  char msg[512];
  snprintf(msg, sizeof msg, "READY=1\nSTATUS=%s", status);
  notify(msg);
}

void service_reloading(void) {
  /* systemd 253 and later want the time of the reload request with RELOADING=1. */
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  char msg[128];
  snprintf(msg, sizeof msg, "RELOADING=1\nMONOTONIC_USEC=%llu",
           (unsigned long long)ts.tv_sec * 1000000ull + (unsigned long long)ts.tv_nsec / 1000u);
  notify(msg);
}

void service_stopping(void) {
  static int sent;
  if (sent)
    return;
  sent = 1;
  notify("STOPPING=1\nSTATUS=stopping");
}
