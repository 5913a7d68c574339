/* pty master as the simulated MCU's UART (see oibar/sim_pty.h). */
#include "oibar/sim_pty.h"

#include "oibar_pty.h"

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

static int s_fd = -1;
static uint32_t s_tx_count;

bool sim_pty_open(char *path, size_t cap)
{
    const int fd = oibar_pty_open_raw(path, cap);
    if (fd < 0) {
        return false;
    }
    s_fd = fd;
    return true;
}

void sim_pty_close(void)
{
    if (s_fd >= 0) {
        (void)close(s_fd);
        s_fd = -1;
    }
}

size_t sim_pty_write(const uint8_t *data, size_t len)
{
    size_t done = 0u;
    while (s_fd >= 0 && done < len) {
        const ssize_t n = write(s_fd, &data[done], len - done);
        if (n <= 0) {
            break; /* EAGAIN (nobody reading) or EIO (no slave): the rest is lost */
        }
        done += (size_t)n;
    }
    s_tx_count += (uint32_t)done;
    return done;
}

uint32_t sim_pty_take_tx_count(void)
{
    const uint32_t n = s_tx_count;
    s_tx_count = 0u;
    return n;
}

size_t sim_pty_read_exact(uint8_t *buf, size_t n, int timeout_ms)
{
    size_t got = 0u;
    while (s_fd >= 0 && got < n) {
        const ssize_t r = read(s_fd, &buf[got], n - got);
        if (r > 0) {
            got += (size_t)r;
            continue;
        }
        if (r < 0 && errno != EAGAIN && errno != EINTR) {
            break;
        }
        /* The bytes are in flight inside the kernel's tty layer: wait. */
        struct pollfd pfd = { s_fd, POLLIN, 0 };
        if (poll(&pfd, 1, timeout_ms) <= 0) {
            break;
        }
    }
    return got;
}
