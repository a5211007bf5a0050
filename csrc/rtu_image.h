/*
 * pyrtu C core: the image of a DataStore, the values a server answers plain reads
 * from without entering Python (csrc/rtu_image.c; portable C99, no I/O, no clock,
 * no thread, no allocation).
 *
 * [AP] MODBUS Application Protocol Specification V1.1b3, 6.1-6.4 (FC 01 Read
 * Coils, 02 Read Discrete Inputs, 03 Read Holding Registers, 04 Read Input
 * Registers).
 *
 * The caller (the Python DataStore) owns every byte: four tables, each an array of
 * ranges sorted by start and not overlapping, each range `count` values in the
 * caller's memory.  A PLAIN range's values are what a read answers; a HELD range
 * is one whose reads Python must make itself (an on_read callback): a read that
 * touches it is deferred.  The image answers only what Python's slave would answer
 * with those values (pyrtu/drivers/slave_base.py _read_bits / _read_registers);
 * everything else (another function, a malformed request, an address outside
 * every range, a held range) is deferred to Python, exceptions included.
 * The pure-Python twin is pyrtu/core/_pure/image.py.
 */
#ifndef RTU_IMAGE_H
#define RTU_IMAGE_H

#include <stddef.h>
#include <stdint.h>

#include "rtu.h"

/* The tables, by index: FC 01 reads table 0, 02 table 1, 03 table 2, 04 table 3. */
#define RTU_IMAGE_COILS 0
#define RTU_IMAGE_DISCRETE_INPUTS 1
#define RTU_IMAGE_HOLDING_REGISTERS 2
#define RTU_IMAGE_INPUT_REGISTERS 3
#define RTU_IMAGE_TABLES 4

/* Range flags */
#define RTU_IMAGE_PLAIN 0 /* a range whose values the image answers */
#define RTU_IMAGE_HELD 1  /* a range whose reads Python must make (an on_read callback) */

/* rtu_image_answer's "not mine": Python answers this request. */
#define RTU_IMAGE_DEFER 1

/* The longest answer PDU: function, byte count, 250 bytes ([AP] 6.3: 125 registers;
 * 6.1: 2000 bits are 250 bytes). */
#define RTU_IMAGE_MAX_ANSWER 253

typedef struct {
    uint32_t start; /* first address, 0..65535 */
    uint32_t count; /* 1..65536, start + count <= 65536 */
    uint32_t flags; /* RTU_IMAGE_PLAIN or RTU_IMAGE_HELD */
    /* count values (a bit is 0 or 1; any nonzero reads as 1), the caller's memory */
    uint16_t *values;
} rtu_image_range;

typedef struct {
    const rtu_image_range *ranges[RTU_IMAGE_TABLES]; /* each sorted by start, not overlapping */
    uint32_t nranges[RTU_IMAGE_TABLES];
} rtu_image;

/* RTU_OK, or RTU_EINVAL: img NULL, a table with ranges but a NULL array, a range
 * with count 0, start > 65535 or start + count > 65536, NULL values, unknown flags,
 * or ranges not sorted by start or overlapping. */
int rtu_image_check(const rtu_image *img);

/* The answer to the request PDU pdu[0..len) from a checked image (rtu_image_check
 * RTU_OK): RTU_OK with out[0..*out_len) the response PDU when all hold:
 *   - len is 5 and pdu[0] is 1..4 (function, address, quantity: [AP] 6.1-6.4);
 *   - the quantity is 1..2000 (0x7D0) for FC 01/02, 1..125 (0x7D) for FC 03/04;
 *   - every address of address .. address + quantity - 1 is below 65536 and lies in
 *     a PLAIN range of the function's table (a read may span adjacent ranges);
 * else RTU_IMAGE_DEFER (out's bytes are then unspecified): never an exception
 * answer, Python answers those.  RTU_EINVAL for a NULL argument or cap below
 * RTU_IMAGE_MAX_ANSWER.  Reads nothing outside the image's arrays and pdu[0..len),
 * writes nothing outside out[0..cap). */
int rtu_image_answer(const rtu_image *img, const uint8_t *pdu, size_t len, uint8_t *out, size_t cap,
                     size_t *out_len);

#endif
