/* Character timing.
 * [SL] 2.5.1.1: a frame ends after a silence of 3.5 character times (t3.5); a
 * silence longer than 1.5 character times (t1.5) inside a frame makes it
 * incomplete.  Above 19200 baud fixed values are recommended: t1.5 = 750 us,
 * t3.5 = 1750 us.
 * [CFW] 4.2.5, table 4.1: above 19200 baud the WEG drives keep the 19200 values,
 * T11bits = 573 us and T3.5x = 2.005 ms. */
#include "rtu.h"

/* round(num / den) for positive values, in integers so that the C core and the
 * pure-Python twin agree to the microsecond. */
static int64_t rtu_div_round(int64_t num, int64_t den) { return (2 * num + den) / (2 * den); }

int rtu_timing_init(rtu_timing *t, uint32_t baudrate, unsigned bits_per_char, int rule)
{
    if (t == NULL || baudrate == 0 || bits_per_char < 7 || bits_per_char > 12) {
        return RTU_EINVAL;
    }
    if (rule != RTU_TIMING_MODBUS && rule != RTU_TIMING_WEG) {
        return RTU_EINVAL;
    }
    const int64_t bits_us = (int64_t)bits_per_char * 1000000;
    t->char_us = rtu_div_round(bits_us, baudrate);
    if (baudrate <= 19200) {
        t->t15_us = rtu_div_round(bits_us * 3, (int64_t)baudrate * 2);
        t->t35_us = rtu_div_round(bits_us * 7, (int64_t)baudrate * 2);
    } else if (rule == RTU_TIMING_MODBUS) {
        t->t15_us = 750;
        t->t35_us = 1750;
    } else {
        t->t15_us = 860; /* 1.5 x 573 us, rounded half up */
        t->t35_us = 2005;
    }
    return RTU_OK;
}
