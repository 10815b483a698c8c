/* Trigger-board line protocol: parser and formatter. See tb_protocol.h and sync/PROTOCOL.md. */
#include "tb_protocol.h"

const tb_kind_spec tb_kinds[TB_KIND_COUNT] = {
    {"HELLO", TB_FROM_HOST, "u"},
    {"RATE", TB_FROM_HOST, "uuu"},
    {"START", TB_FROM_HOST, "uu"},
    {"STOP", TB_FROM_HOST, "u"},
    {"TIME", TB_FROM_HOST, "u"},
    {"FLASH", TB_FROM_HOST, "uu"},
    {"STATUS", TB_FROM_HOST, "u"},
    {"ID", TB_FROM_BOARD, "uuww"},
    {"OK", TB_FROM_BOARD, "u"},
    {"ERR", TB_FROM_BOARD, "uw"},
    {"TIME", TB_FROM_BOARD, "uu"},
    {"PULSE", TB_FROM_BOARD, "uu"},
    {"FLASH", TB_FROM_BOARD, "uu"},
    {"STATUS", TB_FROM_BOARD, "uuuuuu"},
    {"DONE", TB_FROM_BOARD, "u"},
    {"BOOT", TB_FROM_BOARD, "uww"},
};

static const char HEX[] = "0123456789ABCDEF";

uint16_t tb_crc16(const char *data, size_t len) {
    /* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF; "123456789" -> 0x29B1 */
    uint16_t crc = 0xFFFF;
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint8_t)data[i]) << 8;
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

static int hex_value(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1; /* upper case only: with 'a'-'f' too, a flipped bit 5 in the checksum would pass */
}

static int is_word_char(char c) {
    return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' ||
           c == '-';
}

static int name_equals(const char *name, const char *s, size_t len) {
    size_t i;
    for (i = 0; i < len; i++) {
        if (name[i] != s[i]) return 0;
    }
    return name[len] == '\0';
}

int tb_kind_lookup(const char *name, size_t len, uint8_t direction) {
    int k;
    for (k = 0; k < TB_KIND_COUNT; k++) {
        if (tb_kinds[k].direction == direction && name_equals(tb_kinds[k].name, name, len)) return k;
    }
    return -1;
}

/* Parse a canonical unsigned decimal (no sign, no leading zeros) that fits in 64 bits. */
static int parse_u64(const char *s, size_t len, uint64_t *out) {
    uint64_t v = 0;
    size_t i;
    if (len == 0 || len > 20) return 0;
    if (len > 1 && s[0] == '0') return 0;
    for (i = 0; i < len; i++) {
        uint64_t d;
        if (s[i] < '0' || s[i] > '9') return 0;
        d = (uint64_t)(s[i] - '0');
        if (v > (UINT64_MAX - d) / 10u) return 0; /* would overflow */
        v = v * 10u + d;
    }
    *out = v;
    return 1;
}

enum tb_result tb_parse(const char *line, size_t len, uint8_t direction, tb_msg *out) {
    size_t star, i, body_len, pos, tok_start;
    int k, crc_given = 0, argi, wordi;
    const char *types;

    if (len > TB_MAX_LINE) return TB_ERR_LENGTH;

    /* checksum: the last '*' must be followed by exactly four hex digits */
    star = len;
    for (i = len; i > 0; i--) {
        if (line[i - 1] == '*') {
            star = i - 1;
            break;
        }
    }
    if (star == len || len - star != 5) return TB_ERR_CHECKSUM;
    for (i = star + 1; i < len; i++) {
        int h = hex_value(line[i]);
        if (h < 0) return TB_ERR_CHECKSUM;
        crc_given = (crc_given << 4) | h;
    }
    body_len = star;
    if (tb_crc16(line, body_len) != (uint16_t)crc_given) return TB_ERR_CHECKSUM;

    /* characters and spacing */
    for (i = 0; i < body_len; i++) {
        uint8_t c = (uint8_t)line[i];
        if (c < 0x20 || c > 0x7E || c == '*') return TB_ERR_SYNTAX;
    }
    if (body_len == 0 || line[0] == ' ' || line[body_len - 1] == ' ') return TB_ERR_SYNTAX;
    for (i = 1; i < body_len; i++) {
        if (line[i] == ' ' && line[i - 1] == ' ') return TB_ERR_SYNTAX;
    }

    /* keyword: 1-16 capital letters */
    pos = 0;
    while (pos < body_len && line[pos] != ' ') pos++;
    if (pos > 16) return TB_ERR_SYNTAX;
    for (i = 0; i < pos; i++) {
        if (line[i] < 'A' || line[i] > 'Z') return TB_ERR_SYNTAX;
    }
    k = tb_kind_lookup(line, pos, direction);
    if (k < 0) return TB_ERR_UNKNOWN;

    /* count the arguments before converting any */
    types = tb_kinds[k].types;
    {
        size_t want = 0, have = 0;
        while (types[want]) want++;
        for (i = pos; i < body_len; i++) {
            if (line[i] == ' ') have++;
        }
        if (have != want) return TB_ERR_ARGS;
    }

    out->kind = (uint8_t)k;
    out->nargs = 0;
    argi = 0;
    wordi = 0;
    while (pos < body_len) {
        size_t tok_len;
        pos++; /* the single space */
        tok_start = pos;
        while (pos < body_len && line[pos] != ' ') pos++;
        tok_len = pos - tok_start;
        if (types[argi] == 'u') {
            if (!parse_u64(line + tok_start, tok_len, &out->num[argi])) return TB_ERR_ARGS;
        } else {
            if (tok_len == 0 || tok_len > TB_MAX_WORD) return TB_ERR_ARGS;
            for (i = 0; i < tok_len; i++) {
                if (!is_word_char(line[tok_start + i])) return TB_ERR_ARGS;
                out->word[wordi][i] = line[tok_start + i];
            }
            out->word[wordi][tok_len] = '\0';
            out->num[argi] = 0;
            wordi++;
        }
        argi++;
    }
    out->nargs = (uint8_t)argi;
    return TB_OK;
}

int tb_u64_to_dec(uint64_t v, char *buf) {
    /* Repeated subtraction of powers of ten: AVR has no 64-bit divide instruction. */
    static const uint64_t POW10[20] = {10000000000000000000ull,
                                       1000000000000000000ull,
                                       100000000000000000ull,
                                       10000000000000000ull,
                                       1000000000000000ull,
                                       100000000000000ull,
                                       10000000000000ull,
                                       1000000000000ull,
                                       100000000000ull,
                                       10000000000ull,
                                       1000000000ull,
                                       100000000ull,
                                       10000000ull,
                                       1000000ull,
                                       100000ull,
                                       10000ull,
                                       1000ull,
                                       100ull,
                                       10ull,
                                       1ull};
    int n = 0, p;
    for (p = 0; p < 20; p++) {
        char digit = '0';
        while (v >= POW10[p]) {
            v -= POW10[p];
            digit++;
        }
        if (digit != '0' || n > 0 || p == 19) buf[n++] = digit;
    }
    buf[n] = '\0';
    return n;
}

int tb_format(char *buf, size_t cap, const tb_msg *msg) {
    const char *types, *name;
    size_t n = 0, i;
    int argi, wordi = 0;
    char digits[21];
    uint16_t crc;

    if (msg->kind >= TB_KIND_COUNT) return -1;
    name = tb_kinds[msg->kind].name;
    types = tb_kinds[msg->kind].types;
    for (i = 0; name[i]; i++) {
        if (n + 1 >= cap) return -1;
        buf[n++] = name[i];
    }
    for (argi = 0; types[argi]; argi++) {
        const char *text;
        size_t tlen;
        if (types[argi] == 'u') {
            tlen = (size_t)tb_u64_to_dec(msg->num[argi], digits);
            text = digits;
        } else {
            if (wordi >= TB_MAX_WORDS) return -1;
            text = msg->word[wordi++];
            for (tlen = 0; text[tlen]; tlen++) {
                if (tlen >= TB_MAX_WORD || !is_word_char(text[tlen])) return -1;
            }
            if (tlen == 0) return -1;
        }
        if (n + 1 + tlen + 1 >= cap) return -1;
        buf[n++] = ' ';
        for (i = 0; i < tlen; i++) buf[n++] = text[i];
    }
    crc = tb_crc16(buf, n);
    if (n + 5 > TB_MAX_LINE || n + 5 + 1 > cap) return -1;
    buf[n++] = '*';
    buf[n++] = HEX[(crc >> 12) & 0xF];
    buf[n++] = HEX[(crc >> 8) & 0xF];
    buf[n++] = HEX[(crc >> 4) & 0xF];
    buf[n++] = HEX[crc & 0xF];
    buf[n] = '\0';
    return (int)n;
}

const char *tb_result_name(enum tb_result r) {
    switch (r) {
        case TB_OK: return "ok";
        case TB_ERR_LENGTH: return "length";
        case TB_ERR_CHECKSUM: return "checksum";
        case TB_ERR_SYNTAX: return "syntax";
        case TB_ERR_UNKNOWN: return "unknown";
        case TB_ERR_ARGS: return "args";
    }
    return "?";
}
