/* The sample path: the data-ready edge (Timer1 input capture on ICP1), the SPI burst read
 * and the frame, written into a ring buffer that the main loop drains. Nothing here waits
 * for the host: a full ring drops the frame and counts it. */
#ifndef GYRO_SAMPLER_H
#define GYRO_SAMPLER_H

#include <stdint.h>

#include "config.h"
#include "gyro_frame.h"

#ifdef __cplusplus
extern "C" {
#endif

#define GYRO_RING_MASK (GYRO_RING_FRAMES - 1u)

/* Frames waiting for the host: slots tail .. head-1 (mod GYRO_RING_FRAMES). The ISR owns
 * head, the main loop owns tail; both are single bytes, so each side reads the other's
 * index atomically. */
extern uint8_t gyro_ring[GYRO_RING_FRAMES][GYRO_FRAME_SIZE];
extern volatile uint8_t gyro_ring_head;
extern volatile uint8_t gyro_ring_tail;

/* Overruns since start (they also show in the stream as counter gaps; the LED latches on).
 * missed: data-ready edges not served before the next one (the sensor overwrote a sample);
 * dropped: samples read but not framed because the ring was full (host too slow). */
extern volatile uint32_t gyro_missed_samples;
extern volatile uint32_t gyro_dropped_frames;

/* Start Timer1 input capture on the data-ready pin and enable its interrupt. */
void sampler_start(void);

#ifdef __cplusplus
}
#endif

#endif
