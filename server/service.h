/*
 * Notifications to a service manager (systemd's sd_notify protocol): READY=1 once volfxd
 * accepts connections, STOPPING=1 when it begins to stop, RELOADING=1 around a reload, and
 * STATUS= lines saying what it is doing. Each is a no-op unless NOTIFY_SOCKET is set, and when
 * volfxd was built without libsystemd.
 */
#ifndef VOLFX_SERVICE_H
#define VOLFX_SERVICE_H

/* Sends STATUS='fmt...' (printf-formatted). */
void service_status(const char *fmt, ...) __attribute__((format(printf, 1, 2)));

/* Sends READY=1 with STATUS='status'; also ends a reload begun by service_reloading. */
void service_ready(const char *status);

/* Sends RELOADING=1 with the monotonic time systemd asks for. */
void service_reloading(void);

/* Sends STOPPING=1, once; later calls do nothing. */
void service_stopping(void);

#endif
