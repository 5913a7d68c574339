/* pty master as the simulated MCU's UART (see oibar/sim_pty.h). */
#include "oibar/sim_pty.h"

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
    const int fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (fd < 0) {
        return false;
    }
    if (grantpt(fd) != 0 || unlockpt(fd) != 0) {
        (void)close(fd);
        return false;
    }
    struct termios tio;
    if (tcgetattr(fd, &tio) == 0) {
        /* Raw bytes both ways: no echo, no line editing, no CR/LF mapping. */
        tio.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF);
        tio.c_oflag &= ~(tcflag_t)OPOST;
        tio.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
        tio.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
        tio.c_cflag |= (tcflag_t)CS8;
        (void)tcsetattr(fd, TCSANOW, &tio);
    }
    const char *slave = ptsname(fd);
    const int flags = fcntl(fd, F_GETFL);
    if (slave == NULL || flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) {
        (void)close(fd);
        return false;
    }
    (void)snprintf(path, cap, "%s", slave);
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
