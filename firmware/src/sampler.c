/* The sample path (see sampler.h). One interrupt per data-ready edge:
 *
 *   1. Timer1 latched the edge time (ICR1) in hardware, so a late interrupt still knows when
 *      the sample was taken; the number of sensor periods since the previous edge gives the
 *      counter step (1, or more when an edge went unserved: the gap the host sees).
 *   2. If the ring has room: burst-read the three rates (7 SPI bytes at 8 MHz) and encode
 *      the frame straight into the ring slot with the shared encoder (gyro_frame.c).
 *
 * The counter therefore counts the sensor's samples, as docs/gyro-protocol.md requires:
 * a lost sample, for whatever reason, is a gap, never a silent renumbering. */
#include <avr/interrupt.h>
#include <avr/io.h>

#include "config.h"
#include "gyro_frame.h"
#include "sampler.h"
#include "sensor.h"

uint8_t gyro_ring[GYRO_RING_FRAMES][GYRO_FRAME_SIZE];
volatile uint8_t gyro_ring_head;
volatile uint8_t gyro_ring_tail;
volatile uint32_t gyro_missed_samples;
volatile uint32_t gyro_dropped_frames;

static uint16_t last_edge;
static uint16_t counter;
/* Sensor period in Timer1 ticks x 16, tracked (the MEMS clock is only within about 1 %). */
static uint16_t period_x16 = GYRO_TICKS_PER_SAMPLE * 16u;
static uint8_t period_residue; /* what the last update's shift rounded off: no drift */
static uint8_t started;

void sampler_start(void)
{
    GYRO_DRDY_DDR &= (uint8_t)~_BV(GYRO_DRDY_BIT);
    GYRO_LED_DDR |= _BV(GYRO_LED_BIT);
    TIMSK1 = 0;
    TCCR1A = 0;                                  /* normal mode, no outputs */
    TCCR1C = 0;
    TCCR1B = _BV(ICNC1) | _BV(ICES1) | _BV(CS11); /* noise canceller, rising edge, F_CPU/8 */
    TIFR1 = _BV(ICF1);                           /* forget an edge from before */
    TIMSK1 = _BV(ICIE1);
    sei();
}

/* Counter step for an interval of `dt` ticks longer than 1.5 periods: the nearest whole
 * number of periods. Out of line: the division runs only after a lost sample. */
static uint16_t __attribute__((noinline)) gap_step(uint16_t dt, uint16_t period)
{
    uint16_t step = dt / period;

    if ((uint16_t)(dt - step * period) >= (period >> 1))
        step++;
    return step;
}

ISR(TIMER1_CAPT_vect)
{
    uint16_t edge = ICR1;
    uint16_t dt = edge - last_edge;
    uint16_t period = period_x16 >> 4;
    uint8_t head, next, b[6];

    if (started) {
        if (dt < (period >> 1))
            return; /* a glitch on the line, not a sample: keep the previous edge */
        if (dt < period + (period >> 1)) {
            counter += 1; /* the usual case */
            /* period += (dt - period) / 32, with the rounding residue carried over */
            int16_t error = (int16_t)((uint16_t)(dt << 4) - period_x16) + period_residue;
            period_x16 += (uint16_t)(error >> 5);
            period_residue = (uint8_t)(error & 31);
        } else {
            uint16_t step = gap_step(dt, period);
            counter += step;
            gyro_missed_samples += step - 1u;
            GYRO_LED_PORT |= _BV(GYRO_LED_BIT);
        }
    } else {
        started = 1; /* the first sample is counter 0 */
    }
    last_edge = edge;

    head = gyro_ring_head;
    next = (uint8_t)((head + 1u) & GYRO_RING_MASK);
    if (next == gyro_ring_tail) {
        gyro_dropped_frames++;
        GYRO_LED_PORT |= _BV(GYRO_LED_BIT);
        return;
    }

    GYRO_CS_PORT &= (uint8_t)~_BV(GYRO_CS_BIT);
    sensor_spi_transfer(sensor_burst_address);
    b[0] = sensor_spi_transfer(0);
    b[1] = sensor_spi_transfer(0);
    b[2] = sensor_spi_transfer(0);
    b[3] = sensor_spi_transfer(0);
    b[4] = sensor_spi_transfer(0);
    b[5] = sensor_spi_transfer(0);
    GYRO_CS_PORT |= _BV(GYRO_CS_BIT);

    gyro_frame_encode(gyro_ring[head], counter,
                      (int16_t)(((uint16_t)b[0] << 8) | b[1]),
                      (int16_t)(((uint16_t)b[2] << 8) | b[3]),
                      (int16_t)(((uint16_t)b[4] << 8) | b[5]));
    gyro_ring_head = next;
}
