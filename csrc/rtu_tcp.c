/*
 * The answers at the head of a Modbus TCP client's receive buffer (declared in
 * rtu_tcp.h): portable, no I/O; csrc/rtu_tcp_io.c reads the bytes.
 *
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b:
 *   3.1.3 the MBAP header: transaction id ("used for transaction pairing":
 *         the server copies the request's), protocol id (0), length (the unit
 *         id and the PDU that follow), unit id; the length field is the only
 *         delimiter of an ADU in the TCP stream (rtu_mbap_inspect).  A response
 *         whose transaction id pairs with no request waiting (the answer to one
 *         that timed out) is dropped, as pyrtu/tcp/protocol.py always did.
 */
#include "rtu_tcp.h"

#include "rtu.h"

int rtu_tcp_scan(const uint8_t *buf, size_t n, unsigned tid, rtu_tcp_scan_result *s)
{
    if (s == NULL || (buf == NULL && n > 0) || s->used > n)
        return RTU_EINVAL;
    while (s->error == RTU_MBAP_ERR_NONE && s->used < n) {
        const uint8_t *adu = buf + s->used;
        size_t length = 0;
        int error = RTU_MBAP_ERR_NONE;
        int r = rtu_mbap_inspect(adu, n - s->used, &length, &error);
        if (r == RTU_MBAP_INVALID) {
            s->error = error; /* no way to find the next ADU ([TCP] 3.1.3) */
            break;
        }
        if (r != RTU_MBAP_COMPLETE)
            break; /* a partial ADU: more bytes are needed */
        if (s->ans_len == 0 && (((unsigned)adu[0] << 8) | adu[1]) == (tid & 0xFFFFu)) {
            s->ans_off = s->used;
            s->ans_len = length;
        } else {
            s->late++; /* [TCP] 3.1.3: it pairs with no request waiting */
            if (s->ans_len != 0)
                s->late_after++;
        }
        s->used += length;
    }
    return RTU_OK;
}
