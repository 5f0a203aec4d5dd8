/*
 * boxsim: runs the trigger box's firmware in simavr (an ATmega328P at 16 MHz) with its
 * serial line on a pseudo-terminal, for conformd's tests and for trying a box without
 * one (README, "The reference trigger box").
 *
 *   boxsim FIRMWARE.elf LINK
 *
 * LINK becomes a symlink to the pseudo-terminal the host opens (as it would open
 * /dev/ttyACM0). Host bytes reach the firmware at the line's rate (115200 8N1: one per
 * 87 us of simulated time). On standard output, one line each, with the simulated time
 * in microseconds since power-up:
 *   READY <link>                  the line is there
 *   RX_LF <us>                    a host line's last byte went to the firmware
 *   PIN <cameras|flash|led> <0|1> <us>
 * Standard input takes lines that act on the board's inputs:
 *   button              the operator button pressed for 50 ms
 *   rfid <text>         an RFID reader sends <text> and CR LF (9600 8N1 on D3)
 *   charging | ready    the flash-ready input low (charging) or high
 *   quit                end (the device disappears, as a USB adapter unplugged)
 * Simulated time follows real time where the firmware sleeps (simavr's sleep).
 */
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <pty.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include <simavr/avr_ioport.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_time.h>

#define HOST_BYTE_US 87   /* 10 bits at 115200 baud */
#define RFID_BIT_CYCLES 1667 /* 16 MHz / 9600 */
#define BUTTON_PRESS_US 50000

static avr_t *avr;
static int master = -1;
static const char *link_path;

static unsigned char host_queue[4096];
static size_t host_head, host_len;
static int uart_xoff;

static avr_irq_t *uart_input;
static avr_irq_t *pin_button, *pin_rfid, *pin_flash_ready;

/* the RFID reader's bits, start and stop included, each one bit time long */
static unsigned char rfid_bits[8192];
static size_t rfid_at, rfid_count;

static char control[512];
static size_t control_len;

static unsigned long long now_us(void)
{
    return (unsigned long long)avr_cycles_to_usec(avr, avr->cycle);
}

static void say(const char *what, const char *detail, long value)
{
    if (value >= 0)
        printf("%s %s %ld %llu\n", what, detail, value, now_us());
    else
        printf("%s %llu\n", what, now_us());
    fflush(stdout);
}

static void quit(int code)
{
    if (link_path)
        unlink(link_path);
    exit(code);
}

static void uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    unsigned char c = (unsigned char)value;
    /* nobody reading: the byte is lost, as on a real line */
    if (write(master, &c, 1) < 0 && errno != EAGAIN && errno != EIO)
        quit(3);
}

static void uart_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)value; (void)param;
    uart_xoff = 0;
}

static void uart_xoff_cb(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)value; (void)param;
    uart_xoff = 1;
}

static void pin_changed(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    say("PIN", (const char *)param, (long)(value & 1));
}

static avr_cycle_count_t button_release(avr_t *a, avr_cycle_count_t when, void *p)
{
    (void)a; (void)when; (void)p;
    avr_raise_irq(pin_button, 1);
    return 0;
}

static avr_cycle_count_t rfid_next_bit(avr_t *a, avr_cycle_count_t when, void *p)
{
    (void)a; (void)p;
    if (rfid_at >= rfid_count) {
        rfid_at = rfid_count = 0;
        avr_raise_irq(pin_rfid, 1);
        return 0;
    }
    avr_raise_irq(pin_rfid, rfid_bits[rfid_at++]);
    return when + RFID_BIT_CYCLES;
}

static void rfid_send(const char *text)
{
    int idle = rfid_count == 0;
    for (const char *s = text;; s++) {
        unsigned char c = *s ? (unsigned char)*s : '\r';
        if (rfid_count + 40 > sizeof rfid_bits)
            break;
        rfid_bits[rfid_count++] = 0;
        for (int b = 0; b < 8; b++)
            rfid_bits[rfid_count++] = (c >> b) & 1;
        rfid_bits[rfid_count++] = 1;
        if (!*s) {
            /* CR, then LF */
            c = '\n';
            rfid_bits[rfid_count++] = 0;
            for (int b = 0; b < 8; b++)
                rfid_bits[rfid_count++] = (c >> b) & 1;
            rfid_bits[rfid_count++] = 1;
            break;
        }
    }
    if (idle)
        avr_cycle_timer_register(avr, 1, rfid_next_bit, NULL);
}

static void control_line(char *line)
{
    if (!strcmp(line, "button")) {
        avr_raise_irq(pin_button, 0);
        avr_cycle_timer_register_usec(avr, BUTTON_PRESS_US, button_release, NULL);
    } else if (!strncmp(line, "rfid ", 5)) {
        rfid_send(line + 5);
    } else if (!strcmp(line, "charging")) {
        avr_raise_irq(pin_flash_ready, 0);
    } else if (!strcmp(line, "ready")) {
        avr_raise_irq(pin_flash_ready, 1);
    } else if (!strcmp(line, "quit")) {
        quit(0);
    } else {
        fprintf(stderr, "boxsim: unknown control line '%s'\n", line);
    }
}

/* Every host byte time: the control lines, then one host byte to the firmware. */
static avr_cycle_count_t tick(avr_t *a, avr_cycle_count_t when, void *p)
{
    (void)p;
    char buf[256];
    ssize_t n = read(STDIN_FILENO, buf, sizeof buf);
    if (n == 0)
        quit(0); /* the controlling test went away */
    for (ssize_t i = 0; i < n; i++) {
        if (buf[i] == '\n') {
            control[control_len] = 0;
            control_line(control);
            control_len = 0;
        } else if (control_len + 1 < sizeof control) {
            control[control_len++] = buf[i];
        }
    }
    if (host_len == 0) {
        ssize_t got = read(master, host_queue, sizeof host_queue);
        if (got > 0) {
            host_head = 0;
            host_len = (size_t)got;
        }
    }
    if (host_len > 0 && !uart_xoff) {
        unsigned char c = host_queue[host_head++];
        host_len--;
        avr_raise_irq(uart_input, c);
        if (c == '\n')
            say("RX_LF", "", -1);
    }
    return when + avr_usec_to_cycles(a, HOST_BYTE_US);
}

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: boxsim FIRMWARE.elf LINK\n");
        return 2;
    }
    link_path = NULL;
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "boxsim: cannot read firmware %s\n", argv[1]);
        return 1;
    }
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr) {
        fprintf(stderr, "boxsim: simavr has no atmega328p\n");
        return 1;
    }
    avr_init(avr);
    fw.frequency = 16000000;
    avr_load_firmware(avr, &fw);
    avr->log = LOG_ERROR;

    int slave;
    if (openpty(&master, &slave, NULL, NULL, NULL) != 0) {
        perror("boxsim: openpty");
        return 1;
    }
    struct termios t;
    tcgetattr(slave, &t);
    cfmakeraw(&t);
    tcsetattr(slave, TCSANOW, &t);
    fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);
    fcntl(STDIN_FILENO, F_SETFL, fcntl(STDIN_FILENO, F_GETFL) | O_NONBLOCK);
    unlink(argv[2]);
    if (symlink(ttyname(slave), argv[2]) != 0) {
        perror("boxsim: symlink");
        return 1;
    }
    link_path = argv[2];

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~AVR_UART_FLAG_STDIO;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_out, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                            uart_xon, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            uart_xoff_cb, NULL);
    uart_input = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);

    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 4), pin_changed,
                            "cameras");
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 5), pin_changed,
                            "flash");
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 5), pin_changed,
                            "led");
    pin_button = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 2);
    pin_rfid = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 3);
    pin_flash_ready = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 6);
    /* the pull-ups' levels: button up, reader idle, flash ready */
    avr_raise_irq(pin_button, 1);
    avr_raise_irq(pin_rfid, 1);
    avr_raise_irq(pin_flash_ready, 1);

    avr_cycle_timer_register_usec(avr, HOST_BYTE_US, tick, NULL);
    printf("READY %s\n", argv[2]);
    fflush(stdout);
    for (;;) {
        int state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "boxsim: the firmware stopped (state %d)\n", state);
            quit(1);
        }
    }
}
