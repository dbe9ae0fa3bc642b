/* The product build: frames to the host over USB CDC (the Arduino core's stack from
 * Debian's arduino-core-avr). The sample path runs in the Timer1 capture interrupt
 * (sampler.c); this loop only hands finished frames to the USB stack. USB never blocks the
 * sample path: while the host does not read, the ring fills and frames are dropped and
 * counted (a counter gap on the host). */
#include <Arduino.h>

#include "config.h"
#include "sampler.h"
#include "sensor.h"

void setup()
{
    if (sensor_init(GYRO_FULL_SCALE_DPS) == SENSOR_NONE) {
        /* Nothing answered on SPI (or an unsupported range was built in): blink, send
         * nothing. `timedexec gyro check` reports a silent port. */
        GYRO_LED_DDR |= _BV(GYRO_LED_BIT);
        for (;;) {
            GYRO_LED_PORT ^= _BV(GYRO_LED_BIT);
            delay(100);
        }
    }
    sampler_start();
}

void loop()
{
    uint8_t tail = gyro_ring_tail;
    uint8_t head = gyro_ring_head;
    uint8_t n;

    if (head == tail)
        return;
    n = (uint8_t)((head > tail ? head : GYRO_RING_FRAMES) - tail);
    if (n > GYRO_DRAIN_FRAMES)
        n = GYRO_DRAIN_FRAMES;
    /* Returns 0 at once while no program holds the port open (DTR low): the frames are
     * then discarded, as a device that nobody listens to must. */
    Serial.write(gyro_ring[tail], (size_t)n * GYRO_FRAME_SIZE);
    gyro_ring_tail = (uint8_t)((tail + n) & GYRO_RING_MASK);
}
