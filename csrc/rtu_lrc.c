/* LRC for Modbus ASCII mode.
 * [SL] 2.5.2.2 and 6.2.1: the two's complement of the 8-bit sum of the message
 * bytes (address, function, data; not ':' nor CR LF), computed on the binary
 * values before they are encoded as hex characters.  [BV] 6.7.2.3 gives the
 * same rule. */
#include "rtu.h"

uint8_t rtu_lrc(const uint8_t *data, size_t len)
{
    uint8_t sum = 0;
    for (size_t i = 0; i < len; i++) {
        sum = (uint8_t)(sum + data[i]);
    }
    return (uint8_t)(-sum);
}
