/* Sensor bring-up over SPI (see sensor.h). Register writes run at F_CPU/16 = 1 MHz (the
 * MPU-6000's limit for all registers); the sample path then reads the sensor registers at
 * F_CPU/2 = 8 MHz (MPU-6000: up to 20 MHz for sensor and interrupt registers; ICM-42688-P:
 * 24 MHz). SPI mode 3, MSB first. */
#include <avr/io.h>
#include <util/delay.h>

#include "config.h"
#include "sensor.h"

#define READ_BIT 0x80u
#define WHO_AM_I 0x75u /* both parts */

/* MPU-6000 (Register Map rev. 4.2) */
#define MPU_WHO_AM_I_VALUE 0x68u
#define MPU_SMPLRT_DIV 0x19u
#define MPU_CONFIG 0x1Au
#define MPU_GYRO_CONFIG 0x1Bu
#define MPU_INT_PIN_CFG 0x37u
#define MPU_INT_ENABLE 0x38u
#define MPU_GYRO_XOUT_H 0x43u
#define MPU_SIGNAL_PATH_RESET 0x68u
#define MPU_USER_CTRL 0x6Au
#define MPU_PWR_MGMT_1 0x6Bu

/* ICM-42688-P (bank 0) */
#define ICM_WHO_AM_I_VALUE 0x47u
#define ICM_DEVICE_CONFIG 0x11u
#define ICM_INT_CONFIG 0x14u
#define ICM_GYRO_DATA_X1 0x25u
#define ICM_PWR_MGMT0 0x4Eu
#define ICM_GYRO_CONFIG0 0x4Fu
#define ICM_INT_CONFIG1 0x64u
#define ICM_INT_SOURCE0 0x65u
#define ICM_BANK_SEL 0x76u

uint8_t sensor_burst_address;

static void select(void) { GYRO_CS_PORT &= (uint8_t)~_BV(GYRO_CS_BIT); }
static void deselect(void) { GYRO_CS_PORT |= _BV(GYRO_CS_BIT); }

static void write_reg(uint8_t reg, uint8_t value)
{
    select();
    sensor_spi_transfer(reg);
    sensor_spi_transfer(value);
    deselect();
    _delay_us(2);
}

static uint8_t read_reg(uint8_t reg)
{
    uint8_t value;
    select();
    sensor_spi_transfer(reg | READ_BIT);
    value = sensor_spi_transfer(0);
    deselect();
    _delay_us(2);
    return value;
}

/* FS_SEL code for the range: MPU-6000 counts up from 250 °/s, the ICM-42688-P down from
 * 2000 °/s; 0xFF for a range neither has. */
static uint8_t range_code(uint16_t full_scale_dps)
{
    switch (full_scale_dps) {
    case 250: return 0;
    case 500: return 1;
    case 1000: return 2;
    case 2000: return 3;
    default: return 0xFF;
    }
}

static void init_mpu6000(uint8_t fs)
{
    write_reg(MPU_PWR_MGMT_1, 0x80); /* DEVICE_RESET */
    _delay_ms(100);
    write_reg(MPU_SIGNAL_PATH_RESET, 0x07); /* gyro, accel, temp (datasheet: after reset on SPI) */
    _delay_ms(100);
    write_reg(MPU_PWR_MGMT_1, 0x03);        /* clock: PLL on the gyro Z axis */
    write_reg(MPU_USER_CTRL, 0x10);         /* I2C_IF_DIS: SPI only */
    write_reg(MPU_SMPLRT_DIV, 0);           /* 8 kHz / (1 + 0) */
    write_reg(MPU_CONFIG, (uint8_t)((GYRO_EXT_SYNC_SET << 3) | 0)); /* DLPF_CFG 0: 8 kHz */
    write_reg(MPU_GYRO_CONFIG, (uint8_t)(fs << 3));
    write_reg(MPU_INT_PIN_CFG, 0x00);       /* active high, push-pull, 50 us pulse */
    write_reg(MPU_INT_ENABLE, 0x01);        /* DATA_RDY_EN */
    sensor_burst_address = MPU_GYRO_XOUT_H | READ_BIT;
}

static void init_icm42688p(uint8_t fs)
{
    write_reg(ICM_DEVICE_CONFIG, 0x01); /* SOFT_RESET_CONFIG */
    _delay_ms(2);
    write_reg(ICM_BANK_SEL, 0);
    write_reg(ICM_INT_CONFIG, 0x03);    /* INT1: pulsed, push-pull, active high */
    /* INT_TPULSE_DURATION 8 us and de-assert disabled (required at ODR >= 4 kHz);
     * INT_ASYNC_RESET cleared (needed for the INT pin to work). */
    write_reg(ICM_INT_CONFIG1, 0x60);
    write_reg(ICM_INT_SOURCE0, 0x08);   /* UI_DRDY_INT1_EN */
    /* GYRO_FS_SEL (0 = 2000 ... 3 = 250 °/s) and GYRO_ODR 3 = 8 kHz; the anti-alias and UI
     * filters stay at their reset values: their delay belongs in the sensor profile. */
    write_reg(ICM_GYRO_CONFIG0, (uint8_t)(((3u - fs) << 5) | 0x03));
    write_reg(ICM_PWR_MGMT0, 0x0C);     /* gyro low-noise mode, accel off */
    _delay_ms(50);                      /* gyro start-up (45 ms) */
    sensor_burst_address = ICM_GYRO_DATA_X1 | READ_BIT;
}

uint8_t sensor_init(uint16_t full_scale_dps)
{
    uint8_t who, fs = range_code(full_scale_dps);

    GYRO_CS_PORT |= _BV(GYRO_CS_BIT);
    GYRO_CS_DDR |= _BV(GYRO_CS_BIT);
    /* SS (PB0) output, SCK (PB1) and MOSI (PB2) outputs, MISO (PB3) input. */
    DDRB |= _BV(PB0) | _BV(PB1) | _BV(PB2);
    DDRB &= (uint8_t)~_BV(PB3);
    SPCR = _BV(SPE) | _BV(MSTR) | _BV(CPOL) | _BV(CPHA) | _BV(SPR0); /* mode 3, F_CPU/16 */
    SPSR = 0;
    _delay_ms(100); /* sensor power-up */

    if (fs == 0xFF)
        return SENSOR_NONE;
    who = read_reg(WHO_AM_I);
    if (who == MPU_WHO_AM_I_VALUE)
        init_mpu6000(fs);
    else if (who == ICM_WHO_AM_I_VALUE)
        init_icm42688p(fs);
    else
        return SENSOR_NONE;

    SPCR = _BV(SPE) | _BV(MSTR) | _BV(CPOL) | _BV(CPHA); /* F_CPU/4 ... */
    SPSR = _BV(SPI2X);                                    /* ... x2 = F_CPU/2 = 8 MHz */
    return who == MPU_WHO_AM_I_VALUE ? SENSOR_MPU6000 : SENSOR_ICM42688P;
}
