// The firmware's protocol and board logic, run on the host (built by the tests with g++).
//
//   tb_host parse host|board   stdin: one line per input, hex-encoded bytes
//                              stdout: "OK KIND arg..." or "ERR reason" per input
//   tb_host format             stdin: "host|board KIND arg..." ; stdout: the line, or "ERR"
//   tb_host script [BOARD_ID]  a simulated clock: stdin "@T" (advance to board time T us, firing due
//                              pulses) or "@T LINE" (advance, then receive LINE);
//                              stdout: "T LINE" for every line the board sends, T its board time
//   tb_host serve [BOARD_ID]   the board on stdin/stdout in real time (host monotonic clock, us):
//                              give it a pty and talk to it with the host driver
#include <poll.h>
#include <time.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

extern "C" {
#include "../trigger_board/tb_board.h"
#include "../trigger_board/tb_protocol.h"
}

namespace {

int hex_digit(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

int run_parse(const std::string &dir_name) {
    uint8_t dir = dir_name == "board" ? TB_FROM_BOARD : TB_FROM_HOST;
    std::string hex;
    while (std::getline(std::cin, hex)) {
        std::string bytes;
        for (size_t i = 0; i + 1 < hex.size(); i += 2) {
            bytes.push_back(static_cast<char>(hex_digit(hex[i]) * 16 + hex_digit(hex[i + 1])));
        }
        tb_msg m;
        enum tb_result r = tb_parse(bytes.data(), bytes.size(), dir, &m);
        if (r != TB_OK) {
            std::cout << "ERR " << tb_result_name(r) << "\n";
            continue;
        }
        std::cout << "OK " << tb_kinds[m.kind].name;
        const char *types = tb_kinds[m.kind].types;
        int w = 0;
        for (int i = 0; types[i]; i++) {
            if (types[i] == 'u') {
                char d[21];
                tb_u64_to_dec(m.num[i], d);
                std::cout << " " << d;
            } else {
                std::cout << " " << m.word[w++];
            }
        }
        std::cout << "\n";
    }
    return 0;
}

bool parse_u64_text(const std::string &s, uint64_t *out) {
    if (s.empty() || s.size() > 20) return false;
    uint64_t v = 0;
    for (char c : s) {
        if (c < '0' || c > '9') return false;
        uint64_t d = static_cast<uint64_t>(c - '0');
        if (v > (UINT64_MAX - d) / 10u) return false;
        v = v * 10u + d;
    }
    *out = v;
    return true;
}

int run_format() {
    std::string text;
    while (std::getline(std::cin, text)) {
        std::istringstream in(text);
        std::string dir_name, kind;
        in >> dir_name >> kind;
        uint8_t dir = dir_name == "board" ? TB_FROM_BOARD : TB_FROM_HOST;
        int k = tb_kind_lookup(kind.c_str(), kind.size(), dir);
        if (k < 0) {
            std::cout << "ERR\n";
            continue;
        }
        tb_msg m;
        std::memset(&m, 0, sizeof m);
        m.kind = static_cast<uint8_t>(k);
        const char *types = tb_kinds[k].types;
        std::string tok;
        int i = 0, w = 0;
        bool ok = true;
        while (in >> tok) {
            if (!types[i]) {
                ok = false;
                break;
            }
            if (types[i] == 'u') {
                ok = ok && parse_u64_text(tok, &m.num[i]);
            } else if (tok.size() <= TB_MAX_WORD) {
                std::strcpy(m.word[w++], tok.c_str());
            } else {
                ok = false;
            }
            i++;
        }
        ok = ok && types[i] == '\0';
        char line[TB_MAX_LINE + 1];
        int len = ok ? tb_format(line, sizeof line, &m) : -1;
        if (len < 0) {
            std::cout << "ERR\n";
        } else {
            std::cout << line << "\n";
        }
    }
    return 0;
}

// ---- a board on a simulated clock -----------------------------------------------------------------

struct ScriptBoard {
    tb_board board;
    uint64_t now = 0;
};

void script_write(void *ctx, const char *line, int len) {
    auto *s = static_cast<ScriptBoard *>(ctx);
    std::cout << s->now << " " << std::string(line, static_cast<size_t>(len)) << "\n";
}

void script_led(void *ctx, int on) {
    auto *s = static_cast<ScriptBoard *>(ctx);
    std::cout << s->now << " #LED " << on << "\n";
}

// Fire every pulse due by `until`, as the timer interrupt would, reporting each at its edge time.
void advance(ScriptBoard &s, uint64_t until) {
    tb_board *b = &s.board;
    while (tb_board_wants_pulse(b, b->next_index) && tb_board_pulse_time(b, b->next_index) <= until) {
        uint64_t index = b->next_index;
        uint64_t edge = tb_board_pulse_time(b, index);
        b->next_index = index + 1;
        if (edge > s.now) s.now = edge;
        tb_board_pulse_fired(b, index, edge);
        tb_board_poll(b, s.now);
    }
    if (until > s.now) s.now = until;
    tb_board_poll(b, s.now);
}

int run_script(const char *board_id) {
    ScriptBoard s;
    tb_io io = {script_write, script_led, &s};
    tb_board_init(&s.board, &io, board_id);
    tb_board_boot(&s.board);
    std::string text;
    while (std::getline(std::cin, text)) {
        if (text.empty() || text[0] != '@') continue;
        size_t space = text.find(' ');
        uint64_t t = 0;
        if (!parse_u64_text(text.substr(1, space == std::string::npos ? std::string::npos : space - 1), &t)) {
            std::cerr << "bad script line: " << text << "\n";
            return 2;
        }
        advance(s, t);
        if (space != std::string::npos) {
            std::string line = text.substr(space + 1);
            tb_board_line(&s.board, line.data(), static_cast<int>(line.size()), s.now);
        }
    }
    std::cout.flush();
    return 0;
}

// ---- a board in real time on stdin/stdout ---------------------------------------------------------

uint64_t monotonic_us() {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return static_cast<uint64_t>(ts.tv_sec) * 1000000u + static_cast<uint64_t>(ts.tv_nsec) / 1000u;
}

void serve_write(void *, const char *line, int len) {
    std::string out(line, static_cast<size_t>(len));
    out.push_back('\n');
    const char *p = out.data();
    size_t left = out.size();
    while (left > 0) {
        ssize_t n = write(1, p, left);
        if (n <= 0) _exit(0);  // the other end is gone
        p += n;
        left -= static_cast<size_t>(n);
    }
}

int run_serve(const char *board_id) {
    tb_board board;
    tb_io io = {serve_write, nullptr, nullptr};
    tb_board_init(&board, &io, board_id);
    tb_board_boot(&board);
    std::string pending;
    for (;;) {
        uint64_t now = monotonic_us();
        while (tb_board_wants_pulse(&board, board.next_index) && tb_board_pulse_time(&board, board.next_index) <= now) {
            uint64_t index = board.next_index;
            board.next_index = index + 1;
            tb_board_pulse_fired(&board, index, tb_board_pulse_time(&board, index));
        }
        tb_board_poll(&board, now);
        int wait_ms = 50;
        if (tb_board_wants_pulse(&board, board.next_index)) {
            uint64_t due = tb_board_pulse_time(&board, board.next_index);
            wait_ms = due > now ? static_cast<int>((due - now) / 1000u) : 0;
            if (wait_ms > 50) wait_ms = 50;
        }
        struct pollfd pfd = {0, POLLIN, 0};
        int r = poll(&pfd, 1, wait_ms);
        if (r > 0) {
            char buf[256];
            ssize_t n = read(0, buf, sizeof buf);
            if (n <= 0) return 0;
            uint64_t arrival = monotonic_us();
            for (ssize_t i = 0; i < n; i++) {
                if (buf[i] == '\n') {
                    if (!pending.empty() && pending.back() == '\r') pending.pop_back();
                    tb_board_line(&board, pending.data(), static_cast<int>(pending.size()), arrival);
                    pending.clear();
                } else if (pending.size() <= TB_MAX_LINE) {
                    pending.push_back(buf[i]);
                } else {
                    pending.push_back(buf[i]);  // keeps growing past the limit: reported as LENGTH
                    pending.resize(TB_MAX_LINE + 1);
                }
            }
        }
    }
}

}  // namespace

int main(int argc, char **argv) {
    std::string mode = argc > 1 ? argv[1] : "";
    const char *board_id = argc > 2 ? argv[2] : "TB-HOST";
    if (mode == "parse" && argc > 2) return run_parse(argv[2]);
    if (mode == "format") return run_format();
    if (mode == "script") return run_script(board_id);
    if (mode == "serve") return run_serve(board_id);
    std::cerr << "usage: tb_host parse host|board | format | script [ID] | serve [ID]\n";
    return 2;
}
