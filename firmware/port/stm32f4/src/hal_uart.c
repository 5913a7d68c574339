/*
 * USART1 to the companion computer, 115200 8N1.
 *
 * Receive: the RXNE interrupt hands each byte to the attached callback (the
 * link's ring buffer); nothing else happens in the ISR.
 * Transmit: a queue drained by the TXE interrupt. hal_uart_write() copies a
 * whole frame or nothing (a cut frame would only be a CRC error at the host)
 * and never waits.
 */
#include "oibar/hal.h"

#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

/* Power of two. Four worst-case frames (247 bytes): a telemetry frame, a
 * heartbeat, a response and an event can all be queued at once. */
#define UART_TX_QUEUE_BYTES 1024u
_Static_assert((UART_TX_QUEUE_BYTES & (UART_TX_QUEUE_BYTES - 1u)) == 0u, "power of two");

static uint8_t s_tx_buf[UART_TX_QUEUE_BYTES];
static volatile uint32_t s_tx_head; /* written by the main loop only */
static volatile uint32_t s_tx_tail; /* written by the ISR only */
static hal_uart_rx_fn s_rx_fn;

void port_uart_init(const clock_info_t *clk)
{
    port_gpio_alternate(GPIOA, 9u, GPIO_AF_USART1);  /* TX */
    port_gpio_alternate(GPIOA, 10u, GPIO_AF_USART1); /* RX */
    USART1->CR1 = 0u;
    /* OVER8 = 0: BRR = PCLK / baud (mantissa and 4-bit fraction in one). */
    USART1->BRR = (clk->pclk2_hz + BOARD_LINK_BAUD / 2u) / BOARD_LINK_BAUD;
    USART1->CR2 = 0u; /* 1 stop bit */
    USART1->CR3 = 0u; /* no flow control, no DMA */
    /* Receiver on, but no RX interrupt until someone listens (rx_attach). */
    USART1->CR1 = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE;
    nvic_enable(IRQN_USART1, BOARD_PRIO_USART);
}

void hal_uart_rx_attach(hal_uart_rx_fn on_byte)
{
    uint32_t saved = hal_critical_enter();
    s_rx_fn = on_byte;
    if (on_byte != 0) {
        (void)USART1->SR; /* drop whatever arrived before anyone listened */
        (void)USART1->DR;
        USART1->CR1 |= USART_CR1_RXNEIE;
    } else {
        USART1->CR1 &= ~USART_CR1_RXNEIE;
    }
    hal_critical_exit(saved);
}

size_t hal_uart_write(const uint8_t *data, size_t len)
{
    if (data == 0 || len == 0u) {
        return 0u;
    }
    uint32_t head = s_tx_head;
    uint32_t used = head - s_tx_tail; /* free-running indices: wrap is fine */
    if (len > UART_TX_QUEUE_BYTES - used) {
        g_port_diag.uart_tx_refused++;
        return 0u;
    }
    for (size_t i = 0; i < len; i++) {
        s_tx_buf[(head + i) & (UART_TX_QUEUE_BYTES - 1u)] = data[i];
    }
    cpu_dsb(); /* bytes in RAM before the ISR may see the new head */
    s_tx_head = head + (uint32_t)len;
    /* CR1 is shared with the ISR (it clears TXEIE): change it atomically. */
    uint32_t saved = hal_critical_enter();
    USART1->CR1 |= USART_CR1_TXEIE;
    hal_critical_exit(saved);
    return len;
}

/* Bounds on one ISR pass, so it stays short whatever the line does. */
#define UART_RX_BYTES_PER_IRQ 16u
#define UART_TX_BYTES_PER_IRQ 32u

void hal_uart_errors(hal_uart_errors_t *out)
{
    out->rx_errors = g_port_diag.uart_rx_errors;
    out->rx_overruns = g_port_diag.uart_rx_overruns;
}

void USART1_IRQHandler(void)
{
    /* Receive: on silicon one byte per interrupt; a model that hands the
     * next byte over synchronously (QEMU) gets drained in one pass. */
    for (uint32_t n = 0; n < UART_RX_BYTES_PER_IRQ; n++) {
        uint32_t sr = USART1->SR;
        if ((sr & (USART_SR_RXNE | USART_SR_ORE | USART_SR_FE | USART_SR_NF | USART_SR_PE)) == 0u) {
            break;
        }
        /* Reading DR after SR clears RXNE and the error flags. */
        uint8_t byte = (uint8_t)USART1->DR;
        if ((sr & USART_SR_ORE) != 0u) {
            g_port_diag.uart_rx_overruns++;
        }
        if ((sr & (USART_SR_FE | USART_SR_NF | USART_SR_PE)) != 0u) {
            g_port_diag.uart_rx_errors++; /* a damaged byte: the frame CRC will catch it */
        }
        hal_uart_rx_fn fn = s_rx_fn;
        if ((sr & USART_SR_RXNE) != 0u && fn != 0) {
            fn(byte);
        }
    }
    /* Transmit while the data register is free (one byte on silicon, where
     * TXE drops while the shift register is busy). */
    for (uint32_t n = 0; n < UART_TX_BYTES_PER_IRQ; n++) {
        uint32_t tail = s_tx_tail;
        if (tail == s_tx_head) {
            USART1->CR1 &= ~USART_CR1_TXEIE; /* queue empty: stop asking */
            break;
        }
        if ((USART1->SR & USART_SR_TXE) == 0u) {
            break; /* TXE interrupt brings us back */
        }
        USART1->DR = s_tx_buf[tail & (UART_TX_QUEUE_BYTES - 1u)];
        s_tx_tail = tail + 1u;
    }
}

#if defined(OIBAR_QEMU) && OIBAR_QEMU
/* Emulator image only: called by the 1 kHz tick, it runs the USART handler
 * once from the NVIC, in its own priority (so it never races itself). QEMU
 * 7.2's USART raises no TXE interrupt, so without it nothing would go out.
 * Silicon raises its interrupts: the flight image has no such kick. */
void port_uart_service_kick(void)
{
    NVIC_ISPR[IRQN_USART1 >> 5] = 1u << (IRQN_USART1 & 31u);
}
#endif
