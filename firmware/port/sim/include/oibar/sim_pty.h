/* The simulated MCU's UART: the master side of a pseudo-terminal, so the host
 * opens the slave exactly like the board's serial port. */
#ifndef OIBAR_SIM_PTY_H
#define OIBAR_SIM_PTY_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* Open a raw pty master (non-blocking); writes the slave path into `path`.
 * Returns false on failure. */
bool sim_pty_open(char *path, size_t cap);
void sim_pty_close(void);
/* Transmit: as many bytes as the pty takes now (the rest are lost, as on a
 * UART with a full FIFO). Counted for the lockstep reply. */
size_t sim_pty_write(const uint8_t *data, size_t len);
uint32_t sim_pty_take_tx_count(void);
/* Read exactly `n` bytes the host is known to have written, waiting at most
 * `timeout_ms` for them to cross the pty. Returns how many were read. */
size_t sim_pty_read_exact(uint8_t *buf, size_t n, int timeout_ms);

#endif /* OIBAR_SIM_PTY_H */
