/* Cycle-accurate bench of the gyro firmware on simavr (Debian's libsimavr-dev).
 *
 * Runs an ATmega32u4 ELF at 16 MHz with a model of the sensor on its SPI bus and measures the
 * sample path: from the data-ready edge the model raises on ICP1 (PD4) to the RETI of the
 * Timer1 capture interrupt that framed the sample. The sensor model answers WHO_AM_I
 * (MPU-6000 0x68 or ICM-42688-P 0x47), logs the register writes, and holds a new sample in
 * its gyro registers at every edge (random values, with sync-like bytes A5 5A in a fraction
 * of them). The bytes the firmware sends are captured, and so are the samples the model
 * produced, so a test can check the frames end to end; every interrupt's duration and the
 * longest stretch with interrupts off in each context are measured.
 *
 * usage: sim-bench ELF [--sensor mpu|icm] [--samples N] [--skip-every M] [--clock-ppm P]
 *                      [--seed S] [--out FILE] [--truth FILE] [--sof] [--usb-host]
 *                      [--usb-packets-per-ms N] [--poke ADDR=VALUE]...
 * --out: the bytes the firmware sends (UART, or the emulated USB endpoint with --usb-host);
 * --truth: the samples the model produced (int16 x, y, z each, native byte order).
 * Prints one JSON object on stdout. simavr does not simulate a USB host: by default the USB
 * build sees no host (frames discarded); --usb-host emulates one on the CDC IN endpoint
 * (with --poke to mark the device configured and the port open) and --sof its 1 ms frames.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "avr_ioport.h"
#include "avr_spi.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_interrupts.h"
#include "sim_irq.h"
#include "sim_regbit.h"

#define F_CPU 16000000.0
#define VEC_TIMER1_CAPT 16 /* iom32u4.h: TIMER1_CAPT_vect_num */
#define VEC_USB_GEN 10
#define VEC_USB_COM 11
#define VEC_TIMER0_OVF 23
#define MAX_VEC 43

static avr_t *avr;
static avr_irq_t *drdy_pin;
static avr_spi_t *spi;
static uint8_t spi_out;
static FILE *uart_out, *truth_out;

/* sensor model */
static uint8_t regs[128];
static uint8_t data_base, cs_low, txn_pos, txn_addr, txn_read;
static int icm;
static long writes;
static char write_log[4096];
static size_t write_log_len;

/* edges */
static double period_cycles;
static avr_cycle_count_t first_edge_cycle;
static long samples_target, edges_raised, samples_made, skip_every;
static uint64_t rng_state = 0x9E3779B97F4A7C15ull;
static int started;
static avr_cycle_count_t edge_cycle[64];
static int pulse_cycles;

/* measurements */
static avr_cycle_count_t isr_enter[MAX_VEC + 1];
static unsigned long isr_count[MAX_VEC + 1];
static avr_cycle_count_t isr_max[MAX_VEC + 1], isr_sum[MAX_VEC + 1], isr_min[MAX_VEC + 1];
static avr_cycle_count_t path_max, path_sum, latency_max;
static unsigned long paths;
static long first_served_edge = -1; /* the sample the firmware numbered 0 */
static long pending_edge = -1; /* index of the edge whose capture ISR has not yet returned */
static unsigned long uart_bytes;
static int running_vec;                       /* vector being serviced, 0 = main loop */
static avr_cycle_count_t masked_since, masked_max[MAX_VEC + 1]; /* I flag clear, per context */
static int masked_ctx = -1;
static int pokes;
static uint16_t poke_addr[8];
static uint8_t poke_val[8];
static int sof;                               /* emulate the USB start-of-frame interrupt */
static avr_int_vector_t *usb_gen;
static int usb_host;                          /* an ideal host on the CDC data endpoint */
static uint8_t ep_fill, ep_full_waiting;
static long packets_per_ms, packets_this_ms;   /* host's bulk IN polls per frame, 0 = unlimited */
static unsigned long usb_bytes, usb_packets;

static uint64_t next_random(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

static void cs_changed(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    cs_low = value == 0;
    txn_pos = 0;
}

/* MISO byte of the transfer that sent `value` on MOSI. */
static uint8_t sensor_byte(uint8_t value)
{
    uint8_t reply = 0xFF;
    if (cs_low) {
        if (txn_pos == 0) {
            txn_addr = value & 0x7F;
            txn_read = (value & 0x80) != 0;
            reply = 0;
        } else if (txn_read) {
            reply = regs[(txn_addr + txn_pos - 1) & 0x7F];
        } else {
            uint8_t reg = (txn_addr + txn_pos - 1) & 0x7F;
            regs[reg] = (uint8_t)value;
            writes++;
            if (write_log_len + 16 < sizeof write_log)
                write_log_len += (size_t)snprintf(write_log + write_log_len,
                                                  sizeof write_log - write_log_len, "%s[%u,%u]",
                                                  write_log_len ? "," : "", reg, value & 0xFF);
        }
        txn_pos++;
    }
    return reply;
}

/* SPI master timing. Debian's simavr 1.6 completes every SPI byte after a fixed 100 us
 * whatever the clock; this bench replaces its SPDR write handler with the datasheet's
 * timing: 8 SCK periods of F_CPU / {4, 16, 64, 128}[SPR1:SPR0], halved by SPI2X. */
static avr_cycle_count_t spi_done(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)when; (void)param;
    spi->input_data_register = sensor_byte(spi_out); /* what simavr's SPDR read returns */
    avr_raise_interrupt(a, &spi->spi); /* SPIF */
    return 0;
}

static void spdr_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    static const uint8_t divider[4] = {4, 16, 64, 128};
    uint32_t cycles;
    (void)addr; (void)param;
    avr_regbit_clear(a, spi->spi.raised);
    if (!avr_regbit_get(a, spi->spe) || !avr_regbit_get(a, spi->mstr))
        return;
    cycles = 8u * divider[avr_regbit_get(a, spi->spr[0]) | (avr_regbit_get(a, spi->spr[1]) << 1)];
    if (avr_regbit_get(a, spi->spr[2]))
        cycles >>= 1;
    spi_out = v;
    avr_cycle_timer_register(a, cycles, spi_done, NULL);
}

static avr_cycle_count_t drdy_low(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a; (void)when; (void)param;
    avr_raise_irq(drdy_pin, 0);
    return 0;
}

/* One sensor sample: new register contents, then the data-ready pulse (unless skipped). */
static avr_cycle_count_t sample_edge(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    int16_t v[3];
    int i;
    (void)param;
    for (i = 0; i < 3; i++) {
        uint64_t r = next_random();
        v[i] = (int16_t)(r >> 16);
        if ((r & 0xF) == 0) /* 1 in 16: bytes A5 5A (little-endian 0x5AA5) inside the payload */
            v[i] = (int16_t)0x5AA5;
        regs[data_base + 2 * i] = (uint8_t)((uint16_t)v[i] >> 8); /* big-endian registers */
        regs[data_base + 2 * i + 1] = (uint8_t)v[i];
    }
    if (truth_out)
        fwrite(v, sizeof v, 1, truth_out);
    samples_made++;
    if (skip_every > 0 && samples_made % skip_every == 0) {
        /* the sensor took this sample, but its edge never reached the MCU */
    } else {
        edge_cycle[edges_raised & 63] = when;
        edges_raised++;
        avr_raise_irq(drdy_pin, 1);
        avr_cycle_timer_register(a, (avr_cycle_count_t)pulse_cycles, drdy_low, NULL);
    }
    if (samples_made >= samples_target)
        return 0;
    return first_edge_cycle + (avr_cycle_count_t)(samples_made * period_cycles + 0.5);
}

static void isr_running(struct avr_irq_t *irq, uint32_t value, void *param)
{
    int v = (int)(intptr_t)param;
    (void)irq;
    running_vec = value ? v : 0;
    if (value) {
        isr_enter[v] = avr->cycle;
        if (v == VEC_TIMER1_CAPT && pending_edge < 0 && edges_raised > 0) {
            pending_edge = edges_raised - 1;
            if (first_served_edge < 0)
                first_served_edge = samples_made - 1;
            avr_cycle_count_t lat = avr->cycle - edge_cycle[pending_edge & 63];
            if (lat > latency_max)
                latency_max = lat;
        }
    } else {
        avr_cycle_count_t d = avr->cycle - isr_enter[v];
        isr_count[v]++;
        isr_sum[v] += d;
        if (d > isr_max[v]) isr_max[v] = d;
        if (isr_min[v] == 0 || d < isr_min[v]) isr_min[v] = d;
        if (v == VEC_TIMER1_CAPT && pending_edge >= 0) {
            avr_cycle_count_t p = avr->cycle - edge_cycle[pending_edge & 63];
            paths++;
            path_sum += p;
            if (p > path_max) path_max = p;
            pending_edge = -1;
        }
    }
}

static void uart_byte(struct avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t b = (uint8_t)value;
    (void)irq; (void)param;
    uart_bytes++;
    if (uart_out)
        fwrite(&b, 1, 1, uart_out);
}

/* USB start of frame every 1 ms, as a host sends it: the flag the Arduino core's
 * USB_GEN_vect handles (UDINT.SOFI), and the interrupt. */
static avr_cycle_count_t sof_tick(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)param;
    avr_core_watch_write(a, 0xE1, a->data[0xE1] | 0x04); /* UDINT |= SOFI */
    packets_this_ms = 0;
    if (ep_full_waiting) {
        ep_fill = 0;
        ep_full_waiting = 0;
        packets_this_ms = 1;
    }
    avr_raise_interrupt(a, usb_gen);
    return when + (avr_cycle_count_t)(F_CPU / 1000);
}

/* An ideal host on the CDC IN endpoint (--usb-host): the bank accepts bytes until it holds
 * 64 (RWAL), and a released bank is taken at once. Replaces simavr's USB registers so that
 * the Arduino core's USB_Send copy loop runs as it does on a board whose host keeps up. */
#define R_UEINTX 0xE8
#define R_UEDATX 0xF1
#define R_UEBCLX 0xF2
static uint8_t ep_read(struct avr_t *a, avr_io_addr_t addr, void *param)
{
    (void)a; (void)param;
    if (addr == R_UEBCLX)
        return ep_fill;
    return (uint8_t)((ep_fill < 64 ? 0x20 : 0) | 0x01 | 0x80); /* RWAL, TXINI, FIFOCON */
}

static void ep_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)a; (void)param;
    if (addr == R_UEDATX) {
        if (ep_fill < 64) {
            ep_fill++;
            usb_bytes++;
            if (uart_out)
                fwrite(&v, 1, 1, uart_out);
        }
    } else if (addr == R_UEINTX && !(v & 0x80) && ep_fill) { /* FIFOCON cleared: release */
        usb_packets++;
        if (packets_per_ms && ++packets_this_ms > packets_per_ms) {
            ep_fill = 64; /* the host takes this bank at the next frame */
            ep_full_waiting = 1;
        } else {
            ep_fill = 0;
        }
    }
}

/* The firmware enabled the sensor's data-ready interrupt: start the sample clock. */
static void maybe_start(void)
{
    int enabled = icm ? (regs[0x65] & 0x08) && (regs[0x4E] & 0x0C) : (regs[0x38] & 0x01);
    if (!started && enabled) {
        int j;
        started = 1;
        for (j = 0; j < pokes; j++)
            avr->data[poke_addr[j]] = poke_val[j];
        if (sof && usb_gen)
            avr_cycle_timer_register(avr, (avr_cycle_count_t)(F_CPU / 1000), sof_tick, NULL);
        first_edge_cycle = avr->cycle + (avr_cycle_count_t)period_cycles;
        avr_cycle_timer_register(avr, (avr_cycle_count_t)period_cycles, sample_edge, NULL);
    }
}

int main(int argc, char **argv)
{
    elf_firmware_t fw;
    const char *elf = NULL, *sensor = "mpu";
    double ppm = 0;
    int i, state;
    unsigned long long cycle_limit;
    samples_target = 8000;

    for (i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--sensor") && i + 1 < argc) sensor = argv[++i];
        else if (!strcmp(argv[i], "--samples") && i + 1 < argc) samples_target = atol(argv[++i]);
        else if (!strcmp(argv[i], "--skip-every") && i + 1 < argc) skip_every = atol(argv[++i]);
        else if (!strcmp(argv[i], "--clock-ppm") && i + 1 < argc) ppm = atof(argv[++i]);
        else if (!strcmp(argv[i], "--seed") && i + 1 < argc) rng_state ^= strtoull(argv[++i], NULL, 0) * 0x2545F4914F6CDD1Dull;
        else if (!strcmp(argv[i], "--out") && i + 1 < argc) uart_out = fopen(argv[++i], "wb");
        else if (!strcmp(argv[i], "--truth") && i + 1 < argc) truth_out = fopen(argv[++i], "wb");
        else if (!strcmp(argv[i], "--sof")) sof = 1;
        else if (!strcmp(argv[i], "--usb-host")) usb_host = sof = 1;
        else if (!strcmp(argv[i], "--usb-packets-per-ms") && i + 1 < argc) packets_per_ms = atol(argv[++i]);
        else if (!strcmp(argv[i], "--poke") && i + 1 < argc && pokes < 8) {
            /* ADDR=VALUE into data memory when sampling starts (e.g. the USB core's state) */
            unsigned a, v;
            if (sscanf(argv[++i], "%i=%i", (int *)&a, (int *)&v) != 2) { fprintf(stderr, "sim-bench: bad --poke\n"); return 2; }
            poke_addr[pokes] = (uint16_t)(a & 0xFFFF);
            poke_val[pokes++] = (uint8_t)v;
        }
        else if (argv[i][0] != '-' && !elf) elf = argv[i];
        else { fprintf(stderr, "sim-bench: bad argument %s\n", argv[i]); return 2; }
    }
    if (!elf || samples_target < 1) {
        fprintf(stderr, "usage: sim-bench ELF [--sensor mpu|icm] [--samples N] ...\n");
        return 2;
    }
    icm = !strcmp(sensor, "icm");
    regs[0x75] = icm ? 0x47 : 0x68;
    data_base = icm ? 0x25 : 0x43;
    pulse_cycles = icm ? 128 : 800; /* 8 us (ICM-42688-P at 8 kHz) or 50 us (MPU-6000) */
    period_cycles = F_CPU / (8000.0 * (1.0 + ppm * 1e-6));

    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw) != 0) {
        fprintf(stderr, "sim-bench: cannot read %s\n", elf);
        return 2;
    }
    strcpy(fw.mmcu, "atmega32u4");
    fw.frequency = (uint32_t)F_CPU;
    avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) { fprintf(stderr, "sim-bench: simavr has no atmega32u4\n"); return 2; }
    avr_init(avr);
    avr->log = 0;
    avr_load_firmware(avr, &fw);

    {
        int io = AVR_DATA_TO_IO(0x4E); /* SPDR (iom32u4.h: _SFR_IO8(0x2E)) */
        spi = (avr_spi_t *)avr->io[io].w.param;
        if (!spi || spi->r_spdr != 0x4E) {
            fprintf(stderr, "sim-bench: simavr's SPI module is not where expected\n");
            return 2;
        }
        avr->io[io].w.c = spdr_write;
    }
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 6), cs_changed, NULL);
    drdy_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 4);
    {
        uint32_t flags = 0;
        avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('1'), &flags);
        flags &= ~(uint32_t)AVR_UART_FLAG_STDIO;
        avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('1'), &flags);
        avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('1'), UART_IRQ_OUTPUT), uart_byte, NULL);
    }
    if (usb_host) {
        avr_io_addr_t regs_usb[3] = {R_UEINTX, R_UEDATX, R_UEBCLX};
        for (i = 0; i < 3; i++) {
            avr->io[AVR_DATA_TO_IO(regs_usb[i])].r.c = ep_read;
            avr->io[AVR_DATA_TO_IO(regs_usb[i])].w.c = ep_write;
        }
    }
    for (i = 0; i < avr->interrupts.vector_count; i++)
        if (avr->interrupts.vector[i] && avr->interrupts.vector[i]->vector == VEC_USB_GEN)
            usb_gen = avr->interrupts.vector[i];
    for (i = 1; i <= MAX_VEC; i++) {
        avr_irq_t *irq = avr_get_interrupt_irq(avr, (uint8_t)i);
        if (irq)
            avr_irq_register_notify(irq + AVR_INT_IRQ_RUNNING, isr_running, (void *)(intptr_t)i);
    }

    /* Boot (sensor set-up waits ~0.35 s), the samples, then 20 ms for the last frames to
     * leave the UART; give up after 5 s of simulated time without a sensor set-up. */
    cycle_limit = (unsigned long long)(5.0 * F_CPU);
    state = cpu_Running;
    while (state != cpu_Done && state != cpu_Crashed) {
        state = avr_run(avr);
        if (first_served_edge >= 0) {
            /* longest stretch with interrupts off, per context (vector, 0 = main loop) */
            if (!avr->sreg[S_I]) {
                if (masked_ctx < 0) { masked_ctx = running_vec; masked_since = avr->cycle; }
            } else if (masked_ctx >= 0) {
                avr_cycle_count_t d = avr->cycle - masked_since;
                if (d > masked_max[masked_ctx]) masked_max[masked_ctx] = d;
                masked_ctx = -1;
            }
        }
        if (!started) {
            maybe_start();
            if (avr->cycle > cycle_limit)
                break;
        } else if (samples_made >= samples_target &&
                   avr->cycle > first_edge_cycle + (avr_cycle_count_t)(samples_target * period_cycles) + (avr_cycle_count_t)(0.02 * F_CPU)) {
            break;
        }
    }
    if (uart_out) fclose(uart_out);
    if (truth_out) fclose(truth_out);

    printf("{\"elf\": \"%s\", \"sensor\": \"%s\", \"f_cpu_hz\": %.0f, \"started\": %d, "
           "\"cpu_state\": %d, \"cycles\": %llu, \"samples_made\": %ld, \"edges_raised\": %ld, "
           "\"period_cycles\": %.3f, \"sample_paths\": %lu, \"path_max_cycles\": %llu, "
           "\"path_mean_cycles\": %.1f, \"latency_max_cycles\": %llu, \"out_bytes\": %lu, "
           "\"first_served_sample\": %ld, "
           "\"sensor_writes\": [%s], \"isr\": {",
           elf, sensor, F_CPU, started, state, (unsigned long long)avr->cycle, samples_made,
           edges_raised, period_cycles, paths, (unsigned long long)path_max,
           paths ? (double)path_sum / paths : 0.0, (unsigned long long)latency_max, uart_bytes + usb_bytes, first_served_edge,
           write_log);
    {
        int first = 1;
        for (i = 1; i <= MAX_VEC; i++) {
            if (!isr_count[i]) continue;
            printf("%s\"%d\": {\"count\": %lu, \"min_cycles\": %llu, \"max_cycles\": %llu, "
                   "\"mean_cycles\": %.1f}", first ? "" : ", ", i, isr_count[i],
                   (unsigned long long)isr_min[i], (unsigned long long)isr_max[i],
                   (double)isr_sum[i] / isr_count[i]);
            first = 0;
        }
    }
    printf("}, \"masked_max_cycles\": {");
    {
        int first = 1;
        for (i = 0; i <= MAX_VEC; i++) {
            if (!masked_max[i]) continue;
            printf("%s\"%d\": %llu", first ? "" : ", ", i, (unsigned long long)masked_max[i]);
            first = 0;
        }
    }
    printf("}, \"usb_bytes\": %lu, \"usb_packets\": %lu}\n", usb_bytes, usb_packets);
    return started ? 0 : 1;
}
