/* Trigger-board line protocol: parser and formatter in plain C (C99, also valid C++).
 *
 * The same message table as sync/protocol.py and sync/PROTOCOL.md. No heap, no printf, no 64-bit
 * division: it runs on an AVR as well as on an RP2040 or a Teensy, and compiles on the host with g++
 * for the tests (tests/sync/test_firmware.py runs it against sync/protocol_vectors.json).
 */
#ifndef TB_PROTOCOL_H
#define TB_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define TB_PROTOCOL_VERSION 1
#define TB_MAX_LINE 100 /* characters, checksum included, newline excluded */
#define TB_MAX_ARGS 6
#define TB_MAX_WORD 24
#define TB_MAX_WORDS 2

enum tb_direction { TB_FROM_HOST = 0, TB_FROM_BOARD = 1 };

/* Why a line was rejected, in the order the checks run. */
enum tb_result {
    TB_OK = 0,
    TB_ERR_LENGTH = 1,
    TB_ERR_CHECKSUM = 2,
    TB_ERR_SYNTAX = 3,
    TB_ERR_UNKNOWN = 4,
    TB_ERR_ARGS = 5
};

/* Message kinds; host-to-board first, then board-to-host. */
enum tb_kind {
    TB_HELLO = 0,
    TB_RATE,
    TB_START,
    TB_STOP,
    TB_TIME_QUERY,
    TB_FLASH_CMD,
    TB_STATUS_QUERY,
    TB_ID,
    TB_OK_REPLY,
    TB_ERR_REPLY,
    TB_TIME_REPLY,
    TB_PULSE,
    TB_FLASH_EVENT,
    TB_STATUS_REPLY,
    TB_DONE,
    TB_BOOT,
    TB_KIND_COUNT
};

typedef struct {
    const char *name;
    uint8_t direction; /* enum tb_direction */
    const char *types; /* one letter per argument: 'u' unsigned 64-bit integer, 'w' word */
} tb_kind_spec;

extern const tb_kind_spec tb_kinds[TB_KIND_COUNT];

/* A parsed message. Integers go to num[i]; the i-th argument that is a word goes to word[j] in order. */
typedef struct {
    uint8_t kind;
    uint8_t nargs;
    uint64_t num[TB_MAX_ARGS];
    char word[TB_MAX_WORDS][TB_MAX_WORD + 1];
} tb_msg;

uint16_t tb_crc16(const char *data, size_t len);

/* Parse one line without its newline (a trailing '\r' must be removed by the caller). */
enum tb_result tb_parse(const char *line, size_t len, uint8_t direction, tb_msg *out);

/* Write the line for `msg` into buf (no newline, NUL-terminated). Returns its length, or -1 when the
 * message is invalid or does not fit in `cap` (cap >= TB_MAX_LINE + 1 always suffices). */
int tb_format(char *buf, size_t cap, const tb_msg *msg);

/* Decimal text of v into buf (at least 21 bytes); returns the number of digits. */
int tb_u64_to_dec(uint64_t v, char *buf);

/* Look up a kind by name and direction; -1 when unknown. */
int tb_kind_lookup(const char *name, size_t len, uint8_t direction);

const char *tb_result_name(enum tb_result r);

#ifdef __cplusplus
}
#endif

#endif
