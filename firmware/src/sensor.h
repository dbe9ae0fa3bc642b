/* The gyro over SPI: MPU-6000 (the format's reference) or ICM-42688-P, told apart by
 * WHO_AM_I. Both give big-endian 16-bit rates in six consecutive registers with the same
 * sensitivity per range (131 / 65.5 / 32.8 / 16.4 LSB per °/s). */
#ifndef GYRO_SENSOR_H
#define GYRO_SENSOR_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

enum sensor_kind {
    SENSOR_NONE = 0,
    SENSOR_MPU6000 = 1,
    SENSOR_ICM42688P = 2,
};

/* First gyro register with the SPI read bit set; the sample path reads 6 bytes from it. */
extern uint8_t sensor_burst_address;

/* Reset and configure the sensor for 8 kHz gyro output, data-ready pulses on its INT pin
 * and `full_scale_dps`; leaves SPI at F_CPU/2 for the sample path. Returns the kind found
 * (SENSOR_NONE if nothing answered). */
uint8_t sensor_init(uint16_t full_scale_dps);

#ifdef __cplusplus
}
#endif

#include <avr/io.h>

/* SPI transfer of one byte (the bus must be selected). */
static inline uint8_t sensor_spi_transfer(uint8_t out)
{
    SPDR = out;
    while (!(SPSR & _BV(SPIF)))
        ;
    return SPDR;
}

#endif
