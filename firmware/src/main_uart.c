/* The UART build: the same sample path, frames out of USART1 (TX = board pin TX/D1) at
 * 2 Mbaud, 8N1, for a board without native USB or a USB-UART adapter of your choice
 * (docs/gyro-protocol.md: a UART needs at least 880 kbit/s). Also what the cycle-accurate
 * simulator runs end to end (tests/test_firmware.py): simavr models the UART, not USB. */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/power.h>

#include "config.h"
#include "sampler.h"
#include "sensor.h"

int main(void)
{
    uint8_t tail = 0;

    clock_prescale_set(clock_div_1);
    UCSR1A = _BV(U2X1);
    UBRR1 = 0; /* F_CPU / (8 x (0 + 1)) = 2 Mbaud with U2X1 (set first: simavr reads both
                  when UBRR is written) */
    UCSR1C = _BV(UCSZ11) | _BV(UCSZ10);
    UCSR1B = _BV(TXEN1);

    if (sensor_init(GYRO_FULL_SCALE_DPS) == SENSOR_NONE) {
        GYRO_LED_DDR |= _BV(GYRO_LED_BIT);
        for (;;) {
            volatile uint32_t spin;
            GYRO_LED_PORT ^= _BV(GYRO_LED_BIT);
            for (spin = 0; spin < 200000UL; spin++)
                ;
        }
    }
    sampler_start();

    for (;;) {
        if (tail != gyro_ring_head) {
            const uint8_t *frame = gyro_ring[tail];
            uint8_t i;
            for (i = 0; i < GYRO_FRAME_SIZE; i++) {
                while (!(UCSR1A & _BV(UDRE1)))
                    ;
                UDR1 = frame[i];
            }
            tail = (uint8_t)((tail + 1u) & GYRO_RING_MASK);
            gyro_ring_tail = tail; /* the slot is free once its last byte is in the UART */
        }
    }
}
