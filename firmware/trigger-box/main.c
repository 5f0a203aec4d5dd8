/*
 * conformd trigger box: reference firmware for an ATmega328P at 16 MHz (Arduino Uno or
 * Nano). Speaks protocol 1 of conformd's README ("The trigger box protocol") on the
 * board's USB serial line at 115200 8N1:
 *
 *   HELLO conformd 1        -> HELLO conformd-uno 1 <firmware>
 *   ARM <seq>               -> ARMED <seq>                (LED on)
 *   FIRE <seq> <exposure>   -> ACK <seq> <box_time_us>    (the pulse's start)
 *   PING                    -> PONG <box_time_us>
 *   events: EVT BUTTON <t>, EVT RFID <tag> <t>, EVT FAULT <code> <text>
 *   refusals: ERR <seq|-> <code> <text>
 *
 * Pins (wiring table in the README, "The reference trigger box"):
 *   D2 (PD2, INT0)  operator button to GND (internal pull-up), debounced
 *   D3 (PD3, INT1)  RFID reader's TX, 9600 8N1 TTL, read in software
 *   D4 (PD4)        camera trigger out, high for the exposure
 *   D5 (PD5)        flash trigger out, high with the cameras'
 *   D6 (PD6)        flash ready in: LOW while the flash charges (pull-up: no flash, ready)
 *   D13 (PB5)       LED: armed
 *
 * The box clock is Timer1 (0.5 us ticks, extended by its overflows); the pulse ends in
 * Timer1's compare interrupt, so its length does not depend on what the main loop does.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define FIRMWARE "fw-1.0.0"
#define BOX_NAME "conformd-uno"
#define MAX_LINE 120
#define MIN_EXPOSURE_US 10UL
#define MAX_EXPOSURE_US 1000000UL
#define DEBOUNCE_US 30000UL
#define MAX_TAG 32

#define PIN_BUTTON PD2
#define PIN_RFID PD3
#define PIN_CAMERAS PD4
#define PIN_FLASH PD5
#define PIN_FLASH_READY PD6
#define PIN_LED PB5

/* ---- box clock: Timer1 at 2 MHz, 32-bit overflow count on top ---- */

static volatile uint32_t overflows;

ISR(TIMER1_OVF_vect) { overflows++; }

/* Timer1 ticks since start (interrupts off while reading). */
static uint64_t ticks_locked(void)
{
    uint16_t low = TCNT1;
    uint32_t high = overflows;
    /* an overflow not yet counted: the count is one behind a low value */
    if ((TIFR1 & _BV(TOV1)) && low < 0x8000)
        high++;
    return ((uint64_t)high << 16) | low;
}

static uint64_t box_time_us(void)
{
    uint8_t s = SREG;
    cli();
    uint64_t t = ticks_locked();
    SREG = s;
    return t / 2;
}

/* ---- the fire pulse: ended by Timer1's compare A at the right overflow ---- */

static volatile uint8_t pulse_on;
static volatile uint32_t pulse_end_high;

ISR(TIMER1_COMPA_vect)
{
    /* the overflow count only (32-bit): the pulse ends within a few cycles of its tick */
    uint32_t high = overflows;
    if ((TIFR1 & _BV(TOV1)) && TCNT1 < 0x8000)
        high++;
    if (pulse_on && high >= pulse_end_high) {
        PORTD &= ~(_BV(PIN_CAMERAS) | _BV(PIN_FLASH));
        pulse_on = 0;
        TIMSK1 &= ~_BV(OCIE1A);
    }
}

/* Starts the pulse; returns its start in microseconds. */
static uint64_t fire(uint32_t exposure_us)
{
    cli();
    PORTD |= _BV(PIN_CAMERAS) | _BV(PIN_FLASH);
    uint64_t start = ticks_locked();
    uint64_t end = start + 2ULL * exposure_us;
    OCR1A = (uint16_t)end;
    pulse_end_high = (uint32_t)(end >> 16);
    pulse_on = 1;
    TIFR1 = _BV(OCF1A);
    TIMSK1 |= _BV(OCIE1A);
    sei();
    return start / 2;
}

/* ---- host line: USART0, received into a ring by its interrupt ---- */

static volatile uint8_t rx_ring[64];
static volatile uint8_t rx_head, rx_tail, rx_overrun;

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A;
    uint8_t c = UDR0;
    uint8_t next = (rx_head + 1) & 63;
    if ((status & (_BV(DOR0) | _BV(FE0))) || next == rx_tail) {
        rx_overrun = 1;
        return;
    }
    rx_ring[rx_head] = c;
    rx_head = next;
}

static int rx_byte(void)
{
    if (rx_tail == rx_head)
        return -1;
    uint8_t c = rx_ring[rx_tail];
    rx_tail = (rx_tail + 1) & 63;
    return c;
}

static void put(const char *s)
{
    while (*s) {
        loop_until_bit_is_set(UCSR0A, UDRE0);
        UDR0 = *s++;
    }
}

static void put_u64(uint64_t v)
{
    char digits[21];
    char *p = digits + sizeof digits - 1;
    *p = 0;
    do {
        *--p = '0' + (char)(v % 10);
        v /= 10;
    } while (v);
    put(p);
}

static void put_line_end(void) { put("\n"); }

static void refuse(const char *seq, const char *code, const char *text)
{
    put("ERR ");
    put(seq ? seq : "-");
    put(" ");
    put(code);
    put(" ");
    put(text);
    put_line_end();
}

/* ---- operator button: INT0 falling edge, debounced ---- */

static volatile uint8_t button_pressed;
static volatile uint64_t button_time_us;
static uint64_t button_last_us;
static uint8_t button_seen;

ISR(INT0_vect)
{
    uint64_t t = ticks_locked() / 2;
    /* a bounce is an edge within DEBOUNCE_US of the last; the first press always counts */
    if (!button_pressed && (!button_seen || t - button_last_us >= DEBOUNCE_US)) {
        button_seen = 1;
        button_pressed = 1;
        button_time_us = t;
    }
    button_last_us = t;
}

/* ---- RFID reader: software 9600 8N1 receiver on INT1 + Timer2 ---- */

static volatile uint8_t rfid_ring[64];
static volatile uint8_t rfid_head, rfid_tail, rfid_framing;
static volatile uint8_t soft_bit, soft_byte;

ISR(INT1_vect)
{
    /* a start bit: sample it in its middle (104 ticks of 0.5 us), then every bit */
    EIMSK &= ~_BV(INT1);
    soft_bit = 0;
    soft_byte = 0;
    TCNT2 = 207 - 104;
    TIFR2 = _BV(OCF2A);
    TIMSK2 |= _BV(OCIE2A);
}

ISR(TIMER2_COMPA_vect)
{
    uint8_t level = (PIND & _BV(PIN_RFID)) ? 1 : 0;
    if (soft_bit == 0) {
        if (level) { /* a glitch, not a start bit */
            TIMSK2 &= ~_BV(OCIE2A);
            EIFR = _BV(INTF1);
            EIMSK |= _BV(INT1);
            return;
        }
    } else if (soft_bit <= 8) {
        soft_byte |= (uint8_t)(level << (soft_bit - 1));
    } else {
        if (level) {
            uint8_t next = (rfid_head + 1) & 63;
            if (next != rfid_tail) {
                rfid_ring[rfid_head] = soft_byte;
                rfid_head = next;
            }
        } else {
            rfid_framing = 1;
        }
        TIMSK2 &= ~_BV(OCIE2A);
        EIFR = _BV(INTF1);
        EIMSK |= _BV(INT1);
        return;
    }
    soft_bit++;
}

static int rfid_byte(void)
{
    uint8_t s = SREG;
    cli();
    int c = -1;
    if (rfid_tail != rfid_head) {
        c = rfid_ring[rfid_tail];
        rfid_tail = (rfid_tail + 1) & 63;
    }
    SREG = s;
    return c;
}

/* ---- commands ---- */

static uint8_t armed;
static uint32_t armed_seq;
static char armed_text[11];

/* A decimal number that fits 32 bits; 0 when it is not one. In 32-bit arithmetic:
 * 64-bit multiplication costs the AVR hundreds of cycles a digit, before a FIRE. */
static uint8_t parse_u32(const char *s, uint32_t *out)
{
    if (!s || !*s)
        return 0;
    uint32_t v = 0;
    for (const char *p = s; *p; p++) {
        if (*p < '0' || *p > '9')
            return 0;
        uint8_t d = (uint8_t)(*p - '0');
        if (v > 429496729UL || (v == 429496729UL && d > 5))
            return 0;
        v = v * 10 + d;
    }
    *out = v;
    return 1;
}

static void command(char *line)
{
    char *tok[5];
    uint8_t n = 0;
    for (char *p = strtok(line, " "); p && n < 5; p = strtok(NULL, " "))
        tok[n++] = p;
    if (n == 0) {
        refuse(NULL, "E_EMPTY", "empty line");
        return;
    }
    if (!strcmp(tok[0], "HELLO") && n == 3 && !strcmp(tok[1], "conformd")) {
        put("HELLO " BOX_NAME " 1 " FIRMWARE);
        put_line_end();
    } else if (!strcmp(tok[0], "ARM") && n == 2) {
        uint32_t seq;
        if (!parse_u32(tok[1], &seq)) {
            refuse(NULL, "E_ARGS", "ARM needs a sequence number");
            return;
        }
        armed = 1;
        armed_seq = seq;
        strncpy(armed_text, tok[1], sizeof armed_text - 1);
        PORTB |= _BV(PIN_LED);
        put("ARMED ");
        put(tok[1]);
        put_line_end();
    } else if (!strcmp(tok[0], "FIRE") && n == 3) {
        uint32_t seq, exposure;
        if (!parse_u32(tok[1], &seq)) {
            refuse(NULL, "E_ARGS", "FIRE needs a sequence number");
        } else if (!parse_u32(tok[2], &exposure) || exposure < MIN_EXPOSURE_US ||
                   exposure > MAX_EXPOSURE_US) {
            refuse(tok[1], "E_RANGE", "exposure must be 10 to 1000000 us");
        } else if (pulse_on) {
            refuse(tok[1], "E_BUSY", "the previous pulse is still on");
        } else if (!armed || armed_seq != seq) {
            refuse(tok[1], "E_NOT_ARMED", "not armed for this sequence");
        } else if (!(PIND & _BV(PIN_FLASH_READY))) {
            refuse(tok[1], "E_FLASH", "flash not charged");
        } else {
            uint64_t t = fire(exposure);
            armed = 0;
            PORTB &= ~_BV(PIN_LED);
            put("ACK ");
            put(tok[1]);
            put(" ");
            put_u64(t);
            put_line_end();
        }
    } else if (!strcmp(tok[0], "PING") && n == 1) {
        put("PONG ");
        put_u64(box_time_us());
        put_line_end();
    } else {
        refuse(NULL, "E_UNKNOWN", "unknown command");
    }
}

/* ---- the host line's reader: printable lines of at most MAX_LINE bytes ---- */

static char line[MAX_LINE + 1];
static uint8_t line_len, line_long, line_garbage;

static void host_byte(uint8_t c)
{
    if (c == '\n') {
        if (line_long)
            refuse(NULL, "E_LONG", "line over 120 bytes");
        else if (line_garbage)
            refuse(NULL, "E_GARBAGE", "non-printable byte in line");
        else {
            line[line_len] = 0;
            command(line);
        }
        line_len = 0;
        line_long = 0;
        line_garbage = 0;
    } else if (c == '\r') {
        /* a terminal's line end */
    } else if (c < 0x20 || c > 0x7e) {
        line_garbage = 1;
    } else if (line_len >= MAX_LINE) {
        line_long = 1;
    } else {
        line[line_len++] = (char)c;
    }
}

/* ---- the RFID reader's lines: letters and digits up to CR or LF ---- */

static char tag[MAX_TAG + 1];
static uint8_t tag_len, tag_long;
static uint64_t tag_time_us;

static void rfid_char(uint8_t c)
{
    if (c == '\r' || c == '\n' || c == 0x03) { /* a line's end, or ETX */
        if (tag_long) {
            put("EVT FAULT F_RFID tag over 32 characters");
            put_line_end();
        } else if (tag_len) {
            tag[tag_len] = 0;
            put("EVT RFID ");
            put(tag);
            put(" ");
            put_u64(tag_time_us);
            put_line_end();
        }
        tag_len = 0;
        tag_long = 0;
    } else if ((c >= '0' && c <= '9') || (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z')) {
        if (tag_len == 0)
            tag_time_us = box_time_us();
        if (tag_len >= MAX_TAG)
            tag_long = 1;
        else
            tag[tag_len++] = (char)c;
    }
    /* STX and anything else a reader frames its tag with: skipped */
}

static void setup(void)
{
    /* outputs low before they are outputs: no pulse at power-up */
    PORTD &= ~(_BV(PIN_CAMERAS) | _BV(PIN_FLASH));
    DDRD |= _BV(PIN_CAMERAS) | _BV(PIN_FLASH);
    DDRB |= _BV(PIN_LED);
    /* inputs with pull-ups */
    DDRD &= ~(_BV(PIN_BUTTON) | _BV(PIN_RFID) | _BV(PIN_FLASH_READY));
    PORTD |= _BV(PIN_BUTTON) | _BV(PIN_RFID) | _BV(PIN_FLASH_READY);

    /* USART0 115200 8N1 (double speed, UBRR 16: 2.1% off, as the Arduino core) */
    UCSR0A = _BV(U2X0);
    UBRR0 = 16;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);

    /* Timer1: normal mode, clk/8 = 2 MHz */
    TCCR1A = 0;
    TCCR1B = _BV(CS11);
    TIMSK1 = _BV(TOIE1);

    /* Timer2: CTC at 208 ticks of clk/8 = one bit at 9600 baud */
    TCCR2A = _BV(WGM21);
    TCCR2B = _BV(CS21);
    OCR2A = 207;

    /* INT0 and INT1 on falling edges */
    EICRA = _BV(ISC01) | _BV(ISC11);
    EIFR = _BV(INTF0) | _BV(INTF1);
    EIMSK = _BV(INT0) | _BV(INT1);

    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
}

int main(void)
{
    setup();
    for (;;) {
        int c;
        while ((c = rx_byte()) >= 0)
            host_byte((uint8_t)c);
        if (rx_overrun) {
            rx_overrun = 0;
            put("EVT FAULT F_SERIAL host bytes lost");
            put_line_end();
        }
        while ((c = rfid_byte()) >= 0)
            rfid_char((uint8_t)c);
        if (rfid_framing) {
            rfid_framing = 0;
            put("EVT FAULT F_RFID framing error from the reader");
            put_line_end();
        }
        if (button_pressed) {
            uint64_t t;
            cli();
            t = button_time_us;
            button_pressed = 0;
            sei();
            put("EVT BUTTON ");
            put_u64(t);
            put_line_end();
        }
        /* sleep until an interrupt, unless one came in since the checks */
        cli();
        if (rx_tail == rx_head && rfid_tail == rfid_head && !button_pressed) {
            sleep_enable();
            sei();
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}
