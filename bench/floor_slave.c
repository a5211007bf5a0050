/* The least a slave that keeps t3.5 can do: answer every 8-byte FC 03 request on a
 * serial line with zeros, t3.5 after the request's last byte was read.  A bench
 * floor for bench/bench_client.py (`--drive floor`), not a Modbus slave. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static uint16_t crc16(const uint8_t *p, size_t n)
{
    uint16_t crc = 0xFFFF;
    size_t i;
    int b;
    for (i = 0; i < n; i++) {
        crc ^= p[i];
        for (b = 0; b < 8; b++)
            crc = (crc & 1) ? (uint16_t)((crc >> 1) ^ 0xA001) : (uint16_t)(crc >> 1);
    }
    return crc;
}

int main(int argc, char **argv)
{
    struct termios tio;
    uint8_t req[256], ans[300];
    size_t have = 0;
    int64_t t35;
    int fd;
    if (argc < 3) {
        fprintf(stderr, "usage: floor_slave PATH T35_US\n");
        return 2;
    }
    t35 = (int64_t)atol(argv[2]) * 1000;
    fd = open(argv[1], O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (fd < 0) {
        perror("open");
        return 1;
    }
    tcgetattr(fd, &tio);
    cfmakeraw(&tio);
    tcsetattr(fd, TCSANOW, &tio);
    prctl(PR_SET_TIMERSLACK, 1000UL, 0UL, 0UL, 0UL);
    printf("READY\n");
    fflush(stdout);
    for (;;) {
        struct pollfd p = {fd, POLLIN, 0};
        ssize_t got;
        if (poll(&p, 1, -1) < 0 && errno != EINTR)
            return 1;
        got = read(fd, req + have, sizeof req - have);
        if (got <= 0)
            continue;
        have += (size_t)got;
        if (have >= 8) {
            int64_t at = now_ns() + t35;
            struct timespec ts;
            size_t count = req[5], n = 3 + 2 * count;
            uint16_t crc;
            memset(ans, 0, sizeof ans);
            ans[0] = req[0];
            ans[1] = 3;
            ans[2] = (uint8_t)(2 * count);
            crc = crc16(ans, n);
            ans[n] = (uint8_t)(crc & 0xFF);
            ans[n + 1] = (uint8_t)(crc >> 8);
            ts.tv_sec = at / 1000000000;
            ts.tv_nsec = at % 1000000000;
            while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
            }
            if (write(fd, ans, n + 2) < 0)
                return 1;
            have = 0;
        }
    }
}
