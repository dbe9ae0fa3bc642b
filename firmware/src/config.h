/* Build-time settings of the gyro firmware (ATmega32u4 at 16 MHz: Arduino Micro, Leonardo,
 * Pro Micro 5 V). Pins are the board's labels; see docs/gyro-kit.md for the wiring. */
#ifndef GYRO_CONFIG_H
#define GYRO_CONFIG_H

/* Gyro full-scale range, °/s: 250, 500, 1000 or 2000 (`make FS_DPS=...`). The stream does
 * not carry it: tell the host (`--full-scale-dps`, the sensor profile). */
#ifndef GYRO_FULL_SCALE_DPS
#define GYRO_FULL_SCALE_DPS 500
#endif

/* FSYNC tag for the bench procedures of docs/sensor-constants.md (MPU-6000 EXT_SYNC_SET:
 * 0 = off, 2/3/4 = FSYNC in bit 0 of rate x/y/z). `make EXT_SYNC=2`. */
#ifndef GYRO_EXT_SYNC_SET
#define GYRO_EXT_SYNC_SET 0
#endif

/* Timer1 counts at F_CPU / 8 = 2 MHz: one sample period at 8 kHz is 250 ticks, and a run
 * of up to 262 unserved data-ready edges (32.8 ms, the timer's wrap) is counted exactly. */
#define GYRO_TICKS_PER_SAMPLE 250u

/* Frames the ring buffer holds (a power of two): 128 x 11 bytes = 16 ms at 8 kHz of host
 * or USB hiccup absorbed before a frame is dropped (and counted). */
#define GYRO_RING_FRAMES 128u

/* Frames handed to the USB stack per write: 5 x 11 = 55 bytes, below one 64-byte endpoint
 * bank, which bounds the time the Arduino core keeps interrupts off to copy them. */
#define GYRO_DRAIN_FRAMES 5u

/* Pins (ATmega32u4 ports). SPI: SCK PB1, MOSI PB2, MISO PB3 (the board's SCK/MO/MI pins);
 * PB0 (SS, the RX LED) must stay an output for SPI master mode. */
#define GYRO_CS_DDR DDRB
#define GYRO_CS_PORT PORTB
#define GYRO_CS_BIT 6 /* board pin D10 */
/* Data-ready: PD4 = ICP1 = board pin D4; Timer1 latches the edge time in hardware. */
#define GYRO_DRDY_DDR DDRD
#define GYRO_DRDY_BIT 4
/* Status LED: PC7 = board pin D13 ("L" on the Micro). On = an overrun happened; blinking
 * = no sensor answered on SPI. */
#define GYRO_LED_DDR DDRC
#define GYRO_LED_PORT PORTC
#define GYRO_LED_BIT 7

#endif
