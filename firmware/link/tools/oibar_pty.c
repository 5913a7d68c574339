/* Raw pseudo-terminal for host-built stand-ins of the board (see oibar_pty.h). */
#define _XOPEN_SOURCE 700
#include "oibar_pty.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

static int fail(int fd)
{
    const int saved = errno;
    (void)close(fd);
    errno = saved;
    return -1;
}

int oibar_pty_open_raw(char *path, size_t cap)
{
    const int fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (fd < 0) {
        return -1;
    }
    if (grantpt(fd) != 0 || unlockpt(fd) != 0) {
        return fail(fd);
    }
    struct termios tio;
    if (tcgetattr(fd, &tio) == 0) {
        /* Raw bytes both ways: no echo, no line editing, no CR/LF mapping. */
        tio.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF);
        tio.c_oflag &= ~(tcflag_t)OPOST;
        tio.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
        tio.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
        tio.c_cflag |= (tcflag_t)CS8;
        tio.c_cc[VMIN] = 1;
        tio.c_cc[VTIME] = 0;
        (void)tcsetattr(fd, TCSANOW, &tio);
    }
    const char *slave = ptsname(fd);
    const int flags = fcntl(fd, F_GETFL);
    if (slave == NULL || flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) {
        return fail(fd);
    }
    (void)snprintf(path, cap, "%s", slave);
    return fd;
}
