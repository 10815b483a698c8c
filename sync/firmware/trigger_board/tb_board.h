/* Trigger-board logic without hardware: commands in, replies and events out, the pulse schedule.
 *
 * The sketch (trigger_board.ino) supplies the clock, the serial port and the output pins; the host
 * harness (sync/firmware/host/tb_host.cpp) supplies a simulated or the host's own clock, so the tests
 * run this very code. Pulse k of a train rises at start_us + floor(k * 10^9 / rate_mhz) us: the
 * schedule is exact on the board's clock, with no accumulated rounding.
 */
#ifndef TB_BOARD_H
#define TB_BOARD_H

#include <stdint.h>

#include "tb_protocol.h"

#ifdef __cplusplus
extern "C" {
#endif

#define TB_FIRMWARE_VERSION "1.0.0"
#define TB_MIN_RATE_MHZ 1u           /* 0.001 Hz */
#define TB_MAX_RATE_MHZ 10000000u    /* 10 kHz */
#define TB_MAX_FLASH_MS 60000u
#define TB_START_LEAD_US 2000u       /* the first pulse of a train follows START by this much */

typedef struct tb_board tb_board;

/* What the platform provides. write_line gets a complete line without the newline. */
typedef struct {
    void (*write_line)(void *ctx, const char *line, int len);
    void (*set_led)(void *ctx, int on);
    void *ctx;
} tb_io;

struct tb_board {
    tb_io io;
    const char *board_id;
    /* settings */
    uint32_t rate_mhz;
    uint32_t width_us;
    /* the running train; read by the pulse timer's interrupt, hence volatile */
    volatile uint8_t running;     /* the timer fires pulses */
    uint8_t train;                /* a train was started and its DONE is not sent yet */
    volatile uint64_t start_us;
    volatile uint64_t next_index; /* index of the next pulse to fire */
    volatile uint64_t count;      /* pulses in the train, 0 = until STOP */
    uint64_t reported;            /* pulses already announced with PULSE */
    /* LED flash */
    uint8_t led_on;
    uint64_t led_off_us;
    /* bookkeeping */
    uint32_t bad_lines;
    uint8_t last_kind;
    uint64_t last_n; /* request number of the last executed command (retries are answered, not re-run) */
    char last_reply[TB_MAX_LINE + 1];
    int last_reply_len;
};

void tb_board_init(tb_board *b, const tb_io *io, const char *board_id);

/* Announce the board (BOOT line); call once after the port opens. */
void tb_board_boot(tb_board *b);

/* Handle one received line (without newline or trailing '\r'), read at board time now_us. */
void tb_board_line(tb_board *b, const char *line, int len, uint64_t now_us);

/* Board time of pulse `index` of the running train. */
uint64_t tb_board_pulse_time(const tb_board *b, uint64_t index);

/* Whether the timer should fire pulse `index` (the train runs and has not reached its count). The
 * timer calls this, fires the pulse at tb_board_pulse_time(), then increments next_index. */
int tb_board_wants_pulse(const tb_board *b, uint64_t index);

/* The pulse timer fired pulse `index` (its rising edge was at edge_us): report it. Call from the main
 * loop (never from the interrupt), in index order. */
void tb_board_pulse_fired(tb_board *b, uint64_t index, uint64_t edge_us);

/* Housekeeping from the main loop: switch the LED off when its flash is over; send DONE once a train
 * has ended (count reached or STOP) and every fired pulse has been reported. */
void tb_board_poll(tb_board *b, uint64_t now_us);

#ifdef __cplusplus
}
#endif

#endif
