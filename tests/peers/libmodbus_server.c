/*
 * libmodbus_server: a Modbus RTU slave built on Debian's libmodbus, the
 * interoperability peer of pyrtu's tests and benchmark.
 *
 *   libmodbus_server DEVICE SLAVE [--baud N] [--byte-timeout-ms N]
 *                    [--response-timeout-ms N] [--resync-ms N] [--debug]
 *
 * Opens DEVICE (a serial port or a pseudo-terminal such as a pyrtu.vbus drop)
 * as 8N1 (pseudo-terminals refuse parity), serves slave address SLAVE with
 * modbus_receive / modbus_reply, and exits with status 0 on SIGTERM or SIGINT.
 *
 * Data (the pattern of tests/peers/pattern.py; s is the slave address):
 *   coils              0..1999  (i + s) % 3 == 0
 *   discrete inputs    0..1999  (i * 5 + s) % 7 < 3
 *   holding registers  0..999   (i * 3 + 1 + s * 1000) % 65536
 *   input registers    0..999   (i * 7 + 2 + s * 2000) % 65536
 *
 * Shared bus: libmodbus ignores requests for other addresses and then reads the
 * next message as the other slave's response (confirmation_to_ignore), sized by
 * the response rules, waiting up to the response timeout for it.  After an error
 * (bad CRC, a truncated frame, an overlong count) it has no frame boundary left,
 * so this program resynchronises: it discards input until the line has been
 * silent for --resync-ms (default 1 ms, below the master's t3.5 above 19200 baud).
 *
 * DEVICE "tcp:HOST:PORT" makes it a Modbus TCP server instead (modbus_new_tcp,
 * modbus_tcp_listen): one connection at a time, the next accepted when it closes;
 * it answers every unit id (libmodbus's TCP filter accepts them all).
 *
 * Output on stdout: "READY <device> <slave>" once the port is open, and on exit
 * "STATS replies=R ignored=I crc=C timeouts=T errors=E".
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <time.h>
#include <unistd.h>

#include <modbus.h>

#define N_BITS 2000
#define N_REGS 1000

static volatile sig_atomic_t stop_requested = 0;

static void on_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

static int parse_int(const char *text, long lo, long hi, const char *what)
{
    char *end = NULL;
    long value;

    errno = 0;
    value = strtol(text, &end, 0);
    if (errno != 0 || end == text || *end != '\0' || value < lo || value > hi) {
        fprintf(stderr, "libmodbus_server: bad %s %s (expected %ld..%ld)\n", what, text, lo, hi);
        exit(2);
    }
    return (int)value;
}

static void usage(void)
{
    fprintf(stderr,
            "usage: libmodbus_server DEVICE SLAVE [--baud N] [--byte-timeout-ms N]\n"
            "                        [--response-timeout-ms N] [--resync-ms N] [--debug]\n");
    exit(2);
}

static void fill_pattern(modbus_mapping_t *mb, int s)
{
    int i;

    for (i = 0; i < N_BITS; i++) {
        mb->tab_bits[i] = (uint8_t)((i + s) % 3 == 0);
        mb->tab_input_bits[i] = (uint8_t)((i * 5 + s) % 7 < 3);
    }
    for (i = 0; i < N_REGS; i++) {
        mb->tab_registers[i] = (uint16_t)((i * 3 + 1 + s * 1000) % 65536);
        mb->tab_input_registers[i] = (uint16_t)((i * 7 + 2 + s * 2000) % 65536);
    }
}

/* Discard input until the line has been silent for quiet_us microseconds. */
static void resync(int fd, long quiet_us)
{
    unsigned char sink[256];

    for (;;) {
        fd_set rset;
        struct timeval tv;
        int rc;

        FD_ZERO(&rset);
        FD_SET(fd, &rset);
        tv.tv_sec = quiet_us / 1000000;
        tv.tv_usec = quiet_us % 1000000;
        rc = select(fd + 1, &rset, NULL, NULL, &tv);
        if (rc == 0) {
            return;
        }
        if (rc < 0) {
            if (errno == EINTR && !stop_requested) {
                continue;
            }
            return;
        }
        if (read(fd, sink, sizeof sink) <= 0) {
            return;
        }
    }
}

int main(int argc, char **argv)
{
    const char *device;
    int slave;
    int baud = 115200;
    int byte_timeout_ms = 20;
    int response_timeout_ms = 50;
    int resync_us = 1000;
    int debug = 0;
    int tcp = 0, listener = -1;
    int i;
    modbus_t *ctx;
    modbus_mapping_t *mb;
    struct sigaction sa;
    unsigned long replies = 0, ignored = 0, crc = 0, timeouts = 0, errors = 0;
    uint8_t query[MODBUS_MAX_ADU_LENGTH]; /* 260: a TCP ADU is the longest */

    if (argc < 3) {
        usage();
    }
    device = argv[1];
    slave = parse_int(argv[2], 1, 247, "slave address");
    for (i = 3; i < argc; i++) {
        if (strcmp(argv[i], "--debug") == 0) {
            debug = 1;
        } else if (i + 1 < argc && strcmp(argv[i], "--baud") == 0) {
            baud = parse_int(argv[++i], 50, 4000000, "baud rate");
        } else if (i + 1 < argc && strcmp(argv[i], "--byte-timeout-ms") == 0) {
            byte_timeout_ms = parse_int(argv[++i], 1, 10000, "byte timeout");
        } else if (i + 1 < argc && strcmp(argv[i], "--response-timeout-ms") == 0) {
            response_timeout_ms = parse_int(argv[++i], 1, 10000, "response timeout");
        } else if (i + 1 < argc && strcmp(argv[i], "--resync-ms") == 0) {
            resync_us = 1000 * parse_int(argv[++i], 0, 1000, "resync silence");
        } else {
            usage();
        }
    }

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = 0; /* no SA_RESTART: let select() see the signal */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);

    if (strncmp(device, "tcp:", 4) == 0) {
        char host[256];
        const char *colon = strrchr(device + 4, ':');
        size_t hlen = colon ? (size_t)(colon - (device + 4)) : 0;
        if (colon == NULL || hlen == 0 || hlen >= sizeof host) {
            fprintf(stderr, "libmodbus_server: expected tcp:HOST:PORT, not %s\n", device);
            return 2;
        }
        memcpy(host, device + 4, hlen);
        host[hlen] = '\0';
        tcp = 1;
        ctx = modbus_new_tcp(host, parse_int(colon + 1, 1, 65535, "TCP port"));
    } else {
        ctx = modbus_new_rtu(device, baud, 'N', 8, 1);
    }
    if (ctx == NULL) {
        fprintf(stderr, "libmodbus_server: cannot create a context for %s: %s\n", device,
                modbus_strerror(errno));
        return 1;
    }
    modbus_set_debug(ctx, debug);
    if (modbus_set_slave(ctx, slave) == -1) {
        fprintf(stderr, "libmodbus_server: modbus_set_slave(%d): %s\n", slave, modbus_strerror(errno));
        modbus_free(ctx);
        return 1;
    }
    /* Wake up every 100 ms when idle, to notice SIGTERM (libmodbus retries select on EINTR). */
    modbus_set_indication_timeout(ctx, 0, 100000);
    modbus_set_byte_timeout(ctx, 0, (uint32_t)byte_timeout_ms * 1000U);
    modbus_set_response_timeout(ctx, 0, (uint32_t)response_timeout_ms * 1000U);
    mb = modbus_mapping_new(N_BITS, N_BITS, N_REGS, N_REGS);
    if (mb == NULL) {
        fprintf(stderr, "libmodbus_server: modbus_mapping_new: %s\n", modbus_strerror(errno));
        modbus_free(ctx);
        return 1;
    }
    fill_pattern(mb, slave);
    if (tcp) {
        listener = modbus_tcp_listen(ctx, 4);
        if (listener == -1) {
            fprintf(stderr, "libmodbus_server: cannot listen on %s: %s\n", device,
                    modbus_strerror(errno));
            modbus_mapping_free(mb);
            modbus_free(ctx);
            return 1;
        }
    } else if (modbus_connect(ctx) == -1) {
        fprintf(stderr, "libmodbus_server: cannot open %s: %s\n", device, modbus_strerror(errno));
        modbus_mapping_free(mb);
        modbus_free(ctx);
        return 1;
    }
    printf("READY %s %d\n", device, slave);
    fflush(stdout);

    while (!stop_requested) {
        if (tcp && modbus_get_socket(ctx) == -1) {
            if (modbus_tcp_accept(ctx, &listener) == -1) {
                continue; /* EINTR from SIGTERM: the loop condition decides */
            }
        }
        int rc = modbus_receive(ctx, query);
        if (rc > 0) {
            if (modbus_reply(ctx, query, rc, mb) == -1) {
                errors++;
            } else {
                replies++;
            }
        } else if (rc == 0) {
            ignored++;
        } else if (errno == ETIMEDOUT) {
            timeouts++; /* idle (indication timeout) or a frame cut short */
        } else if (tcp) {
            /* the client closed or sent garbage: drop it, accept the next one */
            if (errno != ECONNRESET) {
                errors++;
            }
            modbus_close(ctx);
            modbus_set_socket(ctx, -1);
        } else {
            if (errno == EMBBADCRC) {
                crc++;
            } else {
                errors++;
            }
            if (debug) {
                fprintf(stderr, "libmodbus_server: %s, resynchronising\n", modbus_strerror(errno));
            }
            resync(modbus_get_socket(ctx), resync_us);
        }
    }

    printf("STATS replies=%lu ignored=%lu crc=%lu timeouts=%lu errors=%lu\n", replies, ignored, crc,
           timeouts, errors);
    fflush(stdout);
    modbus_close(ctx);
    if (listener != -1) {
        close(listener);
    }
    modbus_mapping_free(mb);
    modbus_free(ctx);
    return 0;
}
