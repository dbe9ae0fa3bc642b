/* The gyro frame encoder of docs/gyro-protocol.md: one C source, compiled into the firmware
 * and natively on the host (tests/test_firmware_frames.py checks its bytes against
 * timedexec.sensors' parser).
 *
 * Frame (11 bytes, little-endian):
 *   0  sync 0xA5 | 1  sync 0x5A | 2-3  uint16 sample counter (+1 per sensor sample, wraps)
 *   4-5  int16 rate x | 6-7  int16 rate y | 8-9  int16 rate z (sensor LSB)
 *   10  CRC-8 of bytes 2..9 (poly 0x07, init 0, no reflection, no final XOR: CRC-8/SMBUS)
 */
#ifndef GYRO_FRAME_H
#define GYRO_FRAME_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define GYRO_FRAME_SIZE 11u
#define GYRO_FRAME_SYNC0 0xA5u
#define GYRO_FRAME_SYNC1 0x5Au

/* CRC-8/SMBUS of n bytes; gyro_crc8("123456789", 9) == 0xF4. */
uint8_t gyro_crc8(const uint8_t *data, uint8_t n);

/* Write one frame (GYRO_FRAME_SIZE bytes) for sample `counter` with rates x, y, z (LSB). */
void gyro_frame_encode(uint8_t *frame, uint16_t counter, int16_t x, int16_t y, int16_t z);

#ifdef __cplusplus
}
#endif

#endif
