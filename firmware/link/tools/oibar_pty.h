/*
 * A pseudo-terminal as a serial port, for host-built programs that stand in for the board
 * (the link peer, the simulated MCU): the host software opens the slave path like a real port.
 */
#ifndef OIBAR_PTY_H
#define OIBAR_PTY_H

#include <stddef.h>

/* Open a pty master in raw 8-bit mode (no echo, no line editing, no CR/LF mapping), non-blocking,
 * and write the slave's path into `path`. Returns the master fd, or -1 with errno set. */
int oibar_pty_open_raw(char *path, size_t cap);

#endif
