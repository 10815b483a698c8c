// Camera trigger board: RP2040 (Raspberry Pi Pico) with the arduino-pico core (Earle Philhower).
//
// GP2  trigger output: one pulse per frame to every camera's trigger input (through a line driver
//      or optocoupler as the cameras need); the rising edge is the trigger instant.
// GP3  flash output: an LED (or buzzer) the cameras that cannot be triggered can see (FLASH command).
// USB  the host link, the line protocol of sync/PROTOCOL.md (any baud rate: USB CDC ignores it).
//
// The pulses come from a hardware alarm of the RP2040's 64-bit microsecond timer: the alarm
// interrupt raises the output, notes the edge time and arms the falling edge, which arms the next
// rising edge at start + floor(k * 10^9 / rate_mHz) us. The main loop only talks to the host: it
// reads commands, and reports each fired pulse from a ring buffer the interrupt fills.
//
// Protocol parsing, formatting and command handling are plain C (tb_protocol.c, tb_board.c), built
// on the host by the tests and run against sync/protocol_vectors.json.
#include <Arduino.h>

#include "hardware/gpio.h"
#include "hardware/sync.h"
#include "hardware/timer.h"
#include "pico/unique_id.h"
#include "tb_board.h"
#include "tb_protocol.h"

static const uint TRIGGER_PIN = 2;
static const uint FLASH_PIN = 3;

static tb_board board;
static char board_id[TB_MAX_WORD + 1];

// ---- pulse timer (interrupt side) -----------------------------------------------------------------

struct FiredPulse {
    uint64_t index;
    uint64_t edge_us;
};

static const uint32_t RING_SIZE = 64;  // 2 s of pulses at 30 Hz before the host link must drain it
static volatile FiredPulse ring[RING_SIZE];
static volatile uint32_t ring_head = 0;  // written by the interrupt
static volatile uint32_t ring_tail = 0;  // written by the main loop
static volatile uint32_t ring_overruns = 0;

static int alarm_num = -1;
static volatile bool timer_armed = false;
static volatile bool level_high = false;
static volatile uint64_t current_rise_us = 0;

static void arm_at(uint64_t target_us);

static void on_alarm(uint alarm) {
    (void)alarm;
    if (!level_high) {
        // rising edge of pulse next_index
        gpio_put(TRIGGER_PIN, 1);
        uint64_t edge = time_us_64();
        level_high = true;
        uint64_t index = board.next_index;
        board.next_index = index + 1;
        uint32_t head = ring_head;
        if (head - ring_tail < RING_SIZE) {
            ring[head % RING_SIZE].index = index;
            ring[head % RING_SIZE].edge_us = edge;
            ring_head = head + 1;
        } else {
            ring_overruns++;  // the host link is stuck: the pulse still fires, its report is lost
        }
        arm_at(current_rise_us + board.width_us);
    } else {
        gpio_put(TRIGGER_PIN, 0);
        level_high = false;
        if (tb_board_wants_pulse(&board, board.next_index)) {
            current_rise_us = tb_board_pulse_time(&board, board.next_index);
            arm_at(current_rise_us);
        } else {
            timer_armed = false;
        }
    }
}

static void arm_at(uint64_t target_us) {
    // set_target returns true when the target is already in the past: then fire right away, late
    // (the reported edge time is the real one, so the host still knows when it happened).
    if (hardware_alarm_set_target(alarm_num, from_us_since_boot(target_us))) {
        hardware_alarm_force_irq(alarm_num);
    }
}

static void start_timer_if_needed() {
    uint32_t irq = save_and_disable_interrupts();
    bool arm = !timer_armed && tb_board_wants_pulse(&board, board.next_index);
    if (arm) {
        timer_armed = true;
        level_high = false;
        current_rise_us = tb_board_pulse_time(&board, board.next_index);
    }
    restore_interrupts(irq);
    if (arm) arm_at(current_rise_us);
}

// ---- host link (main loop side) -------------------------------------------------------------------

static void write_line(void *ctx, const char *line, int len) {
    (void)ctx;
    Serial.write(reinterpret_cast<const uint8_t *>(line), static_cast<size_t>(len));
    Serial.write('\n');
}

static void set_flash(void *ctx, int on) {
    (void)ctx;
    gpio_put(FLASH_PIN, on ? 1 : 0);
    digitalWrite(LED_BUILTIN, on ? HIGH : LOW);
}

static char rx[TB_MAX_LINE + 2];
static int rx_len = 0;
static bool rx_overlong = false;
static uint32_t reported_overruns = 0;

void setup() {
    gpio_init(TRIGGER_PIN);
    gpio_set_dir(TRIGGER_PIN, GPIO_OUT);
    gpio_put(TRIGGER_PIN, 0);
    gpio_init(FLASH_PIN);
    gpio_set_dir(FLASH_PIN, GPIO_OUT);
    gpio_put(FLASH_PIN, 0);
    pinMode(LED_BUILTIN, OUTPUT);

    char uid[2 * PICO_UNIQUE_BOARD_ID_SIZE_BYTES + 1];
    pico_get_unique_board_id_string(uid, sizeof uid);
    size_t n = strlen(uid);
    snprintf(board_id, sizeof board_id, "TB-%s", uid + (n > 8 ? n - 8 : 0));

    alarm_num = hardware_alarm_claim_unused(true);
    hardware_alarm_set_callback(alarm_num, on_alarm);

    tb_io io = {write_line, set_flash, nullptr};
    tb_board_init(&board, &io, board_id);
    Serial.begin(115200);
    tb_board_boot(&board);
}

void loop() {
    // 1. report fired pulses in order
    while (ring_tail != ring_head) {
        uint32_t tail = ring_tail;
        uint64_t index = ring[tail % RING_SIZE].index;
        uint64_t edge = ring[tail % RING_SIZE].edge_us;
        ring_tail = tail + 1;
        tb_board_pulse_fired(&board, index, edge);
    }
    if (ring_overruns != reported_overruns) {
        reported_overruns = ring_overruns;
        tb_msg m;
        m.kind = TB_ERR_REPLY;
        m.num[0] = 0;
        strcpy(m.word[0], "OVERRUN");
        char line[TB_MAX_LINE + 1];
        int len = tb_format(line, sizeof line, &m);
        if (len > 0) write_line(nullptr, line, len);
    }

    // 2. commands; a line's time is when its newline arrived (TIME replies carry that instant)
    while (Serial.available() > 0) {
        int c = Serial.read();
        if (c < 0) break;
        if (c == '\n') {
            uint64_t arrival = time_us_64();
            if (rx_len > 0 && rx[rx_len - 1] == '\r') rx_len--;
            if (rx_overlong) {
                rx_len = TB_MAX_LINE + 1;  // reported as a LENGTH error
            }
            tb_board_line(&board, rx, rx_len, arrival);
            rx_len = 0;
            rx_overlong = false;
            start_timer_if_needed();
        } else if (rx_len < TB_MAX_LINE + 1) {
            rx[rx_len++] = static_cast<char>(c);
        } else {
            rx_overlong = true;
        }
    }

    // 3. flash end, end of train
    tb_board_poll(&board, time_us_64());
}
