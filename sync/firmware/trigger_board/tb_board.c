/* Trigger-board logic without hardware. See tb_board.h and sync/PROTOCOL.md. */
#include "tb_board.h"

static const char *const ERROR_CODE[] = {"", "LENGTH", "CHECKSUM", "SYNTAX", "UNKNOWN", "ARGS"};

static void copy_word(char *dst, const char *src) {
    int i = 0;
    while (src[i] && i < TB_MAX_WORD) {
        dst[i] = src[i];
        i++;
    }
    dst[i] = '\0';
}

static int send(tb_board *b, const tb_msg *m, int remember) {
    char line[TB_MAX_LINE + 1];
    int len = tb_format(line, sizeof line, m);
    int i;
    if (len < 0) return -1;
    b->io.write_line(b->io.ctx, line, len);
    if (remember) {
        for (i = 0; i <= len; i++) b->last_reply[i] = line[i];
        b->last_reply_len = len;
    }
    return len;
}

static void reply_ok(tb_board *b, uint64_t n) {
    tb_msg m;
    m.kind = TB_OK_REPLY;
    m.num[0] = n;
    send(b, &m, 1);
}

static void reply_err(tb_board *b, uint64_t n, const char *code) {
    tb_msg m;
    m.kind = TB_ERR_REPLY;
    m.num[0] = n;
    copy_word(m.word[0], code);
    send(b, &m, n != 0);
}

void tb_board_init(tb_board *b, const tb_io *io, const char *board_id) {
    b->io = *io;
    b->board_id = board_id;
    b->rate_mhz = 30000u; /* 30 Hz */
    b->width_us = 100u;
    b->running = 0;
    b->train = 0;
    b->start_us = 0;
    b->next_index = 0;
    b->count = 0;
    b->reported = 0;
    b->led_on = 0;
    b->led_off_us = 0;
    b->bad_lines = 0;
    b->last_n = 0;
    b->last_kind = 0;
    b->last_reply[0] = '\0';
    b->last_reply_len = 0;
}

void tb_board_boot(tb_board *b) {
    tb_msg m;
    m.kind = TB_BOOT;
    m.num[0] = TB_PROTOCOL_VERSION;
    copy_word(m.word[0], TB_FIRMWARE_VERSION);
    copy_word(m.word[1], b->board_id);
    send(b, &m, 0);
}

uint64_t tb_board_pulse_time(const tb_board *b, uint64_t index) {
    /* floor(index * 10^9 / rate): split so the product cannot overflow 64 bits for any index a
     * train can reach (10 kHz for 58 million years) */
    uint64_t whole = index / b->rate_mhz;
    uint64_t rest = index % b->rate_mhz;
    return b->start_us + whole * 1000000000ull + (rest * 1000000000ull) / b->rate_mhz;
}

int tb_board_wants_pulse(const tb_board *b, uint64_t index) {
    return b->running && (b->count == 0 || index < b->count);
}

void tb_board_pulse_fired(tb_board *b, uint64_t index, uint64_t edge_us) {
    tb_msg m;
    m.kind = TB_PULSE;
    m.num[0] = index;
    m.num[1] = edge_us;
    send(b, &m, 0);
    b->reported = index + 1;
}

void tb_board_poll(tb_board *b, uint64_t now_us) {
    if (b->led_on && now_us >= b->led_off_us) {
        b->led_on = 0;
        if (b->io.set_led) b->io.set_led(b->io.ctx, 0);
    }
    if (b->train && b->count != 0 && b->next_index >= b->count) b->running = 0;
    if (b->train && !b->running && b->reported >= b->next_index) {
        tb_msg m;
        b->train = 0;
        m.kind = TB_DONE;
        m.num[0] = b->reported;
        send(b, &m, 0);
    }
}

static void handle(tb_board *b, const tb_msg *cmd, uint64_t now_us) {
    uint64_t n = cmd->num[0];
    tb_msg m;

    /* A retried request (same number and kind: its reply was lost) gets the same reply and is not run
     * twice, so a repeated START cannot restart the train. TIME always answers afresh; HELLO opens a
     * host session and forgets the previous one. */
    if (n != 0 && n == b->last_n && cmd->kind == b->last_kind && b->last_reply_len > 0 &&
        cmd->kind != TB_TIME_QUERY && cmd->kind != TB_HELLO) {
        b->io.write_line(b->io.ctx, b->last_reply, b->last_reply_len);
        return;
    }
    if (cmd->kind != TB_TIME_QUERY) {
        b->last_n = n;
        b->last_kind = cmd->kind;
    }

    switch (cmd->kind) {
        case TB_HELLO:
            m.kind = TB_ID;
            m.num[0] = n;
            m.num[1] = TB_PROTOCOL_VERSION;
            copy_word(m.word[0], TB_FIRMWARE_VERSION);
            copy_word(m.word[1], b->board_id);
            send(b, &m, 1);
            break;
        case TB_RATE: {
            uint64_t rate = cmd->num[1], width = cmd->num[2];
            if (b->train) {
                reply_err(b, n, "BUSY");
            } else if (rate < TB_MIN_RATE_MHZ || rate > TB_MAX_RATE_MHZ || width < 1 ||
                       width >= 1000000000ull / rate) {
                reply_err(b, n, "RANGE"); /* the pulse must end before the next one starts */
            } else {
                b->rate_mhz = (uint32_t)rate;
                b->width_us = (uint32_t)width;
                reply_ok(b, n);
            }
            break;
        }
        case TB_START:
            if (b->train) {
                reply_err(b, n, "BUSY");
            } else {
                b->count = cmd->num[1];
                b->next_index = 0;
                b->reported = 0;
                b->start_us = now_us + TB_START_LEAD_US;
                b->train = 1;
                b->running = 1; /* last: the timer starts reading the train now */
                reply_ok(b, n);
            }
            break;
        case TB_STOP:
            b->running = 0; /* DONE follows from tb_board_poll once fired pulses are reported */
            reply_ok(b, n);
            break;
        case TB_TIME_QUERY:
            m.kind = TB_TIME_REPLY;
            m.num[0] = n;
            m.num[1] = now_us;
            send(b, &m, 0);
            break;
        case TB_FLASH_CMD:
            if (cmd->num[1] < 1 || cmd->num[1] > TB_MAX_FLASH_MS) {
                reply_err(b, n, "RANGE");
                break;
            }
            b->led_on = 1;
            b->led_off_us = now_us + cmd->num[1] * 1000u;
            if (b->io.set_led) b->io.set_led(b->io.ctx, 1);
            reply_ok(b, n);
            m.kind = TB_FLASH_EVENT;
            m.num[0] = now_us;
            m.num[1] = cmd->num[1];
            send(b, &m, 0);
            break;
        case TB_STATUS_QUERY:
            m.kind = TB_STATUS_REPLY;
            m.num[0] = n;
            m.num[1] = b->train;
            m.num[2] = b->rate_mhz;
            m.num[3] = b->width_us;
            m.num[4] = b->reported;
            m.num[5] = b->bad_lines;
            send(b, &m, 1);
            break;
        default:
            reply_err(b, n, "UNKNOWN");
            break;
    }
}

void tb_board_line(tb_board *b, const char *line, int len, uint64_t now_us) {
    tb_msg cmd;
    enum tb_result r;
    if (len == 0) return; /* a blank line (Enter in a terminal) */
    r = tb_parse(line, (size_t)(len < 0 ? 0 : len), TB_FROM_HOST, &cmd);
    if (r != TB_OK) {
        b->bad_lines++;
        reply_err(b, 0, ERROR_CODE[r]); /* the request number is unreadable: 0 */
        return;
    }
    handle(b, &cmd, now_us);
}
