/*
 * rtu_crc.h -- CRC-16/MODBUS for pyrtu.
 *
 * Spec: "Modbus over Serial Line V1.02", 6.2.2 (CRC checking) and Appendix B
 * (CRC generation, the auchCRCHi / auchCRCLo tables), reproduced in Appendix B
 * ("CRC calculation using tables") of the WEG CFW100 / CFW701 Modbus RTU
 * manuals.  Polynomial x^16 + x^15 + x^2 + 1 (0xA001 reflected), init 0xFFFF,
 * no final XOR; check value crc16("123456789") = 0x4B37.  The CRC is appended
 * to an RTU frame low byte first (6.2.2).
 *
 * Every CRC function here takes and returns the *standard* CRC value (the
 * register of the reflected algorithm, not the byte-swapped Modicon pair) and
 * is incremental:
 *
 *     crc = rtu_crc16(a, na, 0xFFFF);
 *     crc = rtu_crc16(b, nb, crc);      // == rtu_crc16(a||b, na+nb, 0xFFFF)
 *
 * `data` may be NULL when `len` is 0.  All functions are thread-safe.
 */
#ifndef RTU_CRC_H
#define RTU_CRC_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Status codes (the same values as csrc/rtu.h). */
#ifndef RTU_OK
#define RTU_OK 0
#endif
#ifndef RTU_EINVAL
#define RTU_EINVAL (-1)
#endif
#ifndef RTU_EUNSUPPORTED
#define RTU_EUNSUPPORTED (-2)
#endif
#ifndef RTU_ENOSPC
#define RTU_ENOSPC (-3)
#endif

/* CRC implementation paths (rtu_crc16_path). */
#define RTU_CRC_BYTEWISE 0 /* Appendix B byte loop with the two 256-byte tables */
#define RTU_CRC_SLICE8 1   /* slicing-by-8, 8 x 256 uint16 tables */
#define RTU_CRC_CLMUL 2    /* PCLMULQDQ folding (x86, pclmul + sse4.1) */
#define RTU_CRC_VCLMUL 3   /* VPCLMULQDQ folding, 512-bit (x86, avx512f/bw/vl + vpclmulqdq) */
#define RTU_CRC_NPATHS 4

#define RTU_CRC_INIT 0xFFFFu
#define RTU_CRC_CHECK 0x4B37u /* crc16("123456789") */

/* The Appendix B tables, generated from 0xA001 (read-only).  The Appendix B
 * loop keeps the register byte-swapped: (uchCRCHi, uchCRCLo) = (crc & 0xFF,
 * crc >> 8), so rtu_auchCRCHi[i] is the low byte of the standard table entry
 * T[i] and rtu_auchCRCLo[i] its high byte. */
extern const uint8_t rtu_auchCRCHi[256];
extern const uint8_t rtu_auchCRCLo[256];

/* Fastest available path for `len` (run-time CPU dispatch). */
uint16_t rtu_crc16(const uint8_t *data, size_t len, uint16_t crc);

/* The individual paths, same semantics as rtu_crc16.  rtu_crc16_clmul and
 * rtu_crc16_vclmul execute PCLMULQDQ / AVX-512 VPCLMULQDQ instructions: call
 * them only when rtu_crc16_path_available() says so (or use rtu_crc16_path,
 * which checks).  On non-x86 builds they are the slicing-by-8 code. */
uint16_t rtu_crc16_bytewise(const uint8_t *data, size_t len, uint16_t crc);
uint16_t rtu_crc16_slice8(const uint8_t *data, size_t len, uint16_t crc);
uint16_t rtu_crc16_clmul(const uint8_t *data, size_t len, uint16_t crc);
uint16_t rtu_crc16_vclmul(const uint8_t *data, size_t len, uint16_t crc);

/* 1 if `path` runs on this CPU, else 0 (also 0 for an unknown path). */
int rtu_crc16_path_available(int path);

/* Run one path: RTU_OK and *out = CRC; RTU_EUNSUPPORTED if this CPU lacks the
 * path; RTU_EINVAL for an unknown path, out == NULL, or data == NULL with
 * len > 0. */
int rtu_crc16_path(int path, const uint8_t *data, size_t len, uint16_t crc, uint16_t *out);

#ifdef __cplusplus
}
#endif

#endif /* RTU_CRC_H */
