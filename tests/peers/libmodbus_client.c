/*
 * libmodbus_client: a Modbus RTU master built on Debian's libmodbus, the
 * interoperability peer of pyrtu's tests and the anchor of its benchmark.
 *
 *   libmodbus_client DEVICE SLAVE [options] bench N [ADDRESS]
 *   libmodbus_client DEVICE SLAVE [options] script OP...
 *
 * options: --baud N (default 115200), --timeout-ms N (response timeout, default
 * 1000), --warmup N (bench: untimed transactions first, default 50), --debug.
 * DEVICE is opened 8N1 (pseudo-terminals refuse parity); DEVICE "tcp:HOST:PORT"
 * speaks Modbus TCP instead (modbus_new_tcp; SLAVE is the unit id, --baud ignored).
 *
 * bench: N transactions of FC 03, 10 holding registers from ADDRESS (default 0),
 * each value checked against the pattern of tests/peers/pattern.py
 * (holding[i] = (i * 3 + 1 + SLAVE * 1000) % 65536).  Prints one JSON line:
 *   {"transactions": N, "errors": E, "wrong": W, "seconds": S,
 *    "cpu_seconds": C, "tps": N/S, "cpu_us_per_tx": C/N*1e6}
 *
 * script: performs the OPs in order and prints one JSON line per OP:
 *   {"op": "r03:0:10", "ok": true, "values": [...]}       reads
 *   {"op": "w06:5:1234", "ok": true}                       writes
 *   {"op": "...", "ok": false, "exception": 2}             exception response
 *   {"op": "...", "ok": false, "errno": N, "error": "..."} no/garbled response
 * OPs (numbers decimal or 0x hex, lists comma separated):
 *   r01:A:N r02:A:N r03:A:N r04:A:N   read coils / discrete / holding / input
 *   w05:A:0|1  w06:A:V  w15:A:b,b,...  w16:A:v,v,...
 *   m22:A:AND:OR                      mask write register
 *   rw23:RA:RN:WA:v,v,...             read/write multiple registers
 *   id17                              report slave id ("pdu": hex of the data)
 *   raw:HEX                           any PDU (function code + data), prints "pdu"
 *   slave:N                           address the following OPs to slave N
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <modbus.h>

#define MAX_VALUES 2000

static void usage(void)
{
    fprintf(stderr,
            "usage: libmodbus_client DEVICE SLAVE [--baud N] [--timeout-ms N] [--warmup N] [--debug]\n"
            "                        bench N [ADDRESS] | script OP...\n");
    exit(2);
}

static long parse_num(const char *text, const char **rest, long lo, long hi, const char *what)
{
    char *end = NULL;
    long value;

    errno = 0;
    value = strtol(text, &end, 0);
    if (errno != 0 || end == text || value < lo || value > hi) {
        fprintf(stderr, "libmodbus_client: bad %s in '%s' (expected %ld..%ld)\n", what, text, lo, hi);
        exit(2);
    }
    if (rest != NULL) {
        *rest = end;
    } else if (*end != '\0') {
        fprintf(stderr, "libmodbus_client: trailing characters after %s in '%s'\n", what, text);
        exit(2);
    }
    return value;
}

/* "A:B:C" -> next number after a ':' (or at the start). */
static long field(const char **p, long lo, long hi, const char *what)
{
    const char *rest = NULL;
    long value;

    if (**p == ':') {
        (*p)++;
    }
    value = parse_num(*p, &rest, lo, hi, what);
    *p = rest;
    return value;
}

/* A comma-separated list after ':'; returns how many values were read. */
static int list(const char **p, uint16_t *out, int max, long hi, const char *what)
{
    int n = 0;

    if (**p == ':') {
        (*p)++;
    }
    for (;;) {
        const char *rest = NULL;
        if (n >= max) {
            fprintf(stderr, "libmodbus_client: too many %s\n", what);
            exit(2);
        }
        out[n++] = (uint16_t)parse_num(*p, &rest, 0, hi, what);
        *p = rest;
        if (**p != ',') {
            break;
        }
        (*p)++;
    }
    return n;
}

static void expect_end(const char *p, const char *op)
{
    if (*p != '\0') {
        fprintf(stderr, "libmodbus_client: trailing characters in '%s'\n", op);
        exit(2);
    }
}

/* After a failed OP the rest of a reply may still be arriving and libmodbus does
 * not flush before a request: wait for it and drop it, so the next OP starts clean. */
static void settle(modbus_t *ctx)
{
    struct timespec pause = {0, 30 * 1000 * 1000};

    nanosleep(&pause, NULL);
    modbus_flush(ctx);
}

static void print_failure(modbus_t *ctx, const char *op)
{
    int e = errno;

    if (e > MODBUS_ENOBASE && e <= MODBUS_ENOBASE + MODBUS_EXCEPTION_GATEWAY_TARGET) {
        printf("{\"op\": \"%s\", \"ok\": false, \"exception\": %d}\n", op, e - MODBUS_ENOBASE);
    } else {
        printf("{\"op\": \"%s\", \"ok\": false, \"errno\": %d, \"error\": \"%s\"}\n", op, e,
               modbus_strerror(e));
    }
    settle(ctx);
}

static void print_regs(const char *op, const uint16_t *v, int n)
{
    int i;

    printf("{\"op\": \"%s\", \"ok\": true, \"values\": [", op);
    for (i = 0; i < n; i++) {
        printf(i ? ", %u" : "%u", (unsigned)v[i]);
    }
    printf("]}\n");
}

static void print_bits(const char *op, const uint8_t *v, int n)
{
    int i;

    printf("{\"op\": \"%s\", \"ok\": true, \"values\": [", op);
    for (i = 0; i < n; i++) {
        printf(i ? ", %s" : "%s", v[i] ? "true" : "false");
    }
    printf("]}\n");
}

static void print_hex(const char *op, const uint8_t *v, int n)
{
    int i;

    printf("{\"op\": \"%s\", \"ok\": true, \"pdu\": \"", op);
    for (i = 0; i < n; i++) {
        printf("%02x", v[i]);
    }
    printf("\"}\n");
}

static int hexval(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

static void run_op(modbus_t *ctx, const char *op)
{
    static uint16_t regs[MAX_VALUES];
    static uint16_t wregs[MAX_VALUES];
    static uint8_t bits[MAX_VALUES];
    static uint8_t buf[MODBUS_MAX_ADU_LENGTH];
    const char *p;
    int rc, n, i;

    if (strncmp(op, "slave:", 6) == 0) {
        p = op + 6;
        modbus_set_slave(ctx, (int)field(&p, 0, 247, "slave"));
        expect_end(p, op);
        printf("{\"op\": \"%s\", \"ok\": true}\n", op);
    } else if (strncmp(op, "r01:", 4) == 0 || strncmp(op, "r02:", 4) == 0) {
        long a, c;
        p = op + 4;
        a = field(&p, 0, 65535, "address");
        c = field(&p, 1, 2000, "count");
        expect_end(p, op);
        rc = op[2] == '1' ? modbus_read_bits(ctx, (int)a, (int)c, bits)
                          : modbus_read_input_bits(ctx, (int)a, (int)c, bits);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            print_bits(op, bits, rc);
        }
    } else if (strncmp(op, "r03:", 4) == 0 || strncmp(op, "r04:", 4) == 0) {
        long a, c;
        p = op + 4;
        a = field(&p, 0, 65535, "address");
        c = field(&p, 1, 125, "count");
        expect_end(p, op);
        rc = op[2] == '3' ? modbus_read_registers(ctx, (int)a, (int)c, regs)
                          : modbus_read_input_registers(ctx, (int)a, (int)c, regs);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            print_regs(op, regs, rc);
        }
    } else if (strncmp(op, "w05:", 4) == 0 || strncmp(op, "w06:", 4) == 0) {
        long a, v;
        p = op + 4;
        a = field(&p, 0, 65535, "address");
        v = field(&p, 0, op[2] == '5' ? 1 : 65535, "value");
        expect_end(p, op);
        rc = op[2] == '5' ? modbus_write_bit(ctx, (int)a, (int)v)
                          : modbus_write_register(ctx, (int)a, (uint16_t)v);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            printf("{\"op\": \"%s\", \"ok\": true}\n", op);
        }
    } else if (strncmp(op, "w15:", 4) == 0 || strncmp(op, "w16:", 4) == 0) {
        long a;
        p = op + 4;
        a = field(&p, 0, 65535, "address");
        n = list(&p, wregs, op[2] == '5' ? 1968 : 123, op[2] == '5' ? 1 : 65535, "values");
        expect_end(p, op);
        if (op[2] == '5') {
            for (i = 0; i < n; i++) {
                bits[i] = (uint8_t)wregs[i];
            }
            rc = modbus_write_bits(ctx, (int)a, n, bits);
        } else {
            rc = modbus_write_registers(ctx, (int)a, n, wregs);
        }
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            printf("{\"op\": \"%s\", \"ok\": true}\n", op);
        }
    } else if (strncmp(op, "m22:", 4) == 0) {
        long a, and_mask, or_mask;
        p = op + 4;
        a = field(&p, 0, 65535, "address");
        and_mask = field(&p, 0, 65535, "AND mask");
        or_mask = field(&p, 0, 65535, "OR mask");
        expect_end(p, op);
        rc = modbus_mask_write_register(ctx, (int)a, (uint16_t)and_mask, (uint16_t)or_mask);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            printf("{\"op\": \"%s\", \"ok\": true}\n", op);
        }
    } else if (strncmp(op, "rw23:", 5) == 0) {
        long ra, rn, wa;
        p = op + 5;
        ra = field(&p, 0, 65535, "read address");
        rn = field(&p, 1, 125, "read count");
        wa = field(&p, 0, 65535, "write address");
        n = list(&p, wregs, 121, 65535, "values");
        expect_end(p, op);
        rc = modbus_write_and_read_registers(ctx, (int)wa, n, wregs, (int)ra, (int)rn, regs);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            print_regs(op, regs, rc);
        }
    } else if (strcmp(op, "id17") == 0) {
        rc = modbus_report_slave_id(ctx, (int)sizeof buf, buf);
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            print_hex(op, buf, rc);
        }
    } else if (strncmp(op, "raw:", 4) == 0) {
        uint8_t req[MODBUS_MAX_ADU_LENGTH];
        size_t len = strlen(op + 4);
        int hi, lo;
        if (len < 2 || len % 2 != 0 || len / 2 + 1 > sizeof req - 2) {
            fprintf(stderr, "libmodbus_client: bad raw PDU '%s'\n", op);
            exit(2);
        }
        req[0] = (uint8_t)modbus_get_slave(ctx);
        for (i = 0; i < (int)(len / 2); i++) {
            hi = hexval(op[4 + 2 * i]);
            lo = hexval(op[5 + 2 * i]);
            if (hi < 0 || lo < 0) {
                fprintf(stderr, "libmodbus_client: bad hex in '%s'\n", op);
                exit(2);
            }
            req[1 + i] = (uint8_t)(hi << 4 | lo);
        }
        rc = modbus_send_raw_request(ctx, req, 1 + (int)(len / 2));
        if (rc >= 0) {
            rc = modbus_receive_confirmation(ctx, buf);
        }
        if (rc < 0) {
            print_failure(ctx, op);
        } else {
            /* ADU -> PDU: drop the address and the CRC (RTU), or the MBAP header (TCP) */
            const int head = modbus_get_header_length(ctx);
            print_hex(op, buf + head, rc - head - (head == 1 ? 2 : 0));
        }
    } else {
        fprintf(stderr, "libmodbus_client: unknown op '%s'\n", op);
        exit(2);
    }
    fflush(stdout);
}

static double now_s(clockid_t clock)
{
    struct timespec ts;

    clock_gettime(clock, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec / 1e9;
}

static int bench(modbus_t *ctx, int slave, long n, int address, long warmup)
{
    uint16_t regs[10];
    long i, errors = 0, wrong = 0;
    int k;
    double t0, c0, t1, c1;

    for (i = 0; i < warmup; i++) {
        if (modbus_read_registers(ctx, address, 10, regs) != 10) {
            errors++;
        }
    }
    if (errors == warmup && warmup > 0) {
        fprintf(stderr, "libmodbus_client: no answer during warm-up: %s\n", modbus_strerror(errno));
        return 1;
    }
    errors = 0;
    t0 = now_s(CLOCK_MONOTONIC);
    c0 = now_s(CLOCK_PROCESS_CPUTIME_ID);
    for (i = 0; i < n; i++) {
        if (modbus_read_registers(ctx, address, 10, regs) != 10) {
            errors++;
            continue;
        }
        for (k = 0; k < 10; k++) {
            if (regs[k] != (uint16_t)(((address + k) * 3 + 1 + slave * 1000) % 65536)) {
                wrong++;
                break;
            }
        }
    }
    t1 = now_s(CLOCK_MONOTONIC);
    c1 = now_s(CLOCK_PROCESS_CPUTIME_ID);
    printf("{\"transactions\": %ld, \"errors\": %ld, \"wrong\": %ld, \"seconds\": %.6f, "
           "\"cpu_seconds\": %.6f, \"tps\": %.1f, \"cpu_us_per_tx\": %.3f}\n",
           n, errors, wrong, t1 - t0, c1 - c0, (double)n / (t1 - t0), (c1 - c0) / (double)n * 1e6);
    fflush(stdout);
    return errors || wrong ? 1 : 0;
}

int main(int argc, char **argv)
{
    const char *device;
    int slave, i, rc = 0;
    int baud = 115200, debug = 0;
    long timeout_ms = 1000, warmup = 50;
    modbus_t *ctx;

    if (argc < 4) {
        usage();
    }
    device = argv[1];
    slave = (int)parse_num(argv[2], NULL, 0, 247, "slave address");
    for (i = 3; i < argc; i++) {
        if (strcmp(argv[i], "--debug") == 0) {
            debug = 1;
        } else if (i + 1 < argc && strcmp(argv[i], "--baud") == 0) {
            baud = (int)parse_num(argv[++i], NULL, 50, 4000000, "baud rate");
        } else if (i + 1 < argc && strcmp(argv[i], "--timeout-ms") == 0) {
            timeout_ms = parse_num(argv[++i], NULL, 1, 60000, "timeout");
        } else if (i + 1 < argc && strcmp(argv[i], "--warmup") == 0) {
            warmup = parse_num(argv[++i], NULL, 0, 1000000, "warm-up count");
        } else {
            break;
        }
    }
    if (i >= argc) {
        usage();
    }

    if (strncmp(device, "tcp:", 4) == 0) {
        char host[256];
        const char *colon = strrchr(device + 4, ':');
        size_t hlen = colon ? (size_t)(colon - (device + 4)) : 0;
        if (colon == NULL || hlen == 0 || hlen >= sizeof host) {
            fprintf(stderr, "libmodbus_client: expected tcp:HOST:PORT, not %s\n", device);
            return 2;
        }
        memcpy(host, device + 4, hlen);
        host[hlen] = '\0';
        ctx = modbus_new_tcp(host, (int)parse_num(colon + 1, NULL, 1, 65535, "TCP port"));
    } else {
        ctx = modbus_new_rtu(device, baud, 'N', 8, 1);
    }
    if (ctx == NULL) {
        fprintf(stderr, "libmodbus_client: cannot create a context for %s: %s\n", device,
                modbus_strerror(errno));
        return 1;
    }
    modbus_set_debug(ctx, debug);
    modbus_set_slave(ctx, slave);
    modbus_set_response_timeout(ctx, (uint32_t)(timeout_ms / 1000), (uint32_t)(timeout_ms % 1000) * 1000U);
    if (modbus_connect(ctx) == -1) {
        fprintf(stderr, "libmodbus_client: cannot open %s: %s\n", device, modbus_strerror(errno));
        modbus_free(ctx);
        return 1;
    }

    if (strcmp(argv[i], "bench") == 0 && (argc - i == 2 || argc - i == 3)) {
        long n = parse_num(argv[i + 1], NULL, 1, 100000000, "transaction count");
        int address = argc - i == 3 ? (int)parse_num(argv[i + 2], NULL, 0, 65526, "address") : 0;
        rc = bench(ctx, slave, n, address, warmup);
    } else if (strcmp(argv[i], "script") == 0) {
        for (i++; i < argc; i++) {
            run_op(ctx, argv[i]);
        }
    } else {
        usage();
    }
    modbus_close(ctx);
    modbus_free(ctx);
    return rc;
}
