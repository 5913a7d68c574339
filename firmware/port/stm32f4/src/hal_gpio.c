/*
 * Digital inputs and outputs by meaning (hal_di_t / hal_do_t); the pin and
 * its polarity come from board.h.
 */
#include "oibar/hal.h"

#include "board.h"
#include "port.h"
#include "stm32f4_regs.h"

static const board_pin_t k_di[HAL_DI_COUNT] = BOARD_DI_PINS;
static const board_pin_t k_do[HAL_DO_COUNT] = BOARD_DO_PINS;

static void set_mode(gpio_regs_t *port, uint32_t pin, uint32_t mode, uint32_t pull)
{
    uint32_t shift = 2u * pin;
    port->PUPDR = (port->PUPDR & ~(3u << shift)) | (pull << shift);
    port->OSPEEDR = (port->OSPEEDR & ~(3u << shift)) | (GPIO_SPEED_MEDIUM << shift);
    port->MODER = (port->MODER & ~(3u << shift)) | (mode << shift);
}

/* BSRR: one store, no read-modify-write, so an ISR and the main loop can
 * drive different pins of one port without a lock. */
static void drive(const board_pin_t *p, bool on)
{
    bool high = on != p->active_low;
    p->port->BSRR = high ? (1u << p->pin) : (1u << (p->pin + 16u));
}

void port_outputs_safe(void)
{
    for (unsigned i = 0; i < (unsigned)HAL_DO_COUNT; i++) {
        drive(&k_do[i], false);
    }
}

void port_gpio_init(void)
{
    /* Latch the safe level into ODR before the pin becomes an output, so it
     * never glitches to the active level. */
    port_outputs_safe();
    for (unsigned i = 0; i < (unsigned)HAL_DO_COUNT; i++) {
        set_mode(k_do[i].port, k_do[i].pin, GPIO_MODE_OUTPUT, GPIO_PULL_NONE);
    }
    for (unsigned i = 0; i < (unsigned)HAL_DI_COUNT; i++) {
        set_mode(k_di[i].port, k_di[i].pin, GPIO_MODE_INPUT, GPIO_PULL_UP);
    }
}

bool hal_di_read(hal_di_t di)
{
    if ((unsigned)di >= (unsigned)HAL_DI_COUNT) {
        return false;
    }
    const board_pin_t *p = &k_di[di];
    bool high = (p->port->IDR & (1u << p->pin)) != 0u;
    return high != p->active_low;
}

void hal_do_write(hal_do_t out, bool on)
{
    if ((unsigned)out < (unsigned)HAL_DO_COUNT) {
        drive(&k_do[out], on);
    }
}

void port_gpio_alternate(gpio_regs_t *port, uint32_t pin, uint32_t af)
{
    uint32_t shift = 4u * (pin & 7u);
    port->AFR[pin >> 3] = (port->AFR[pin >> 3] & ~(0xFu << shift)) | (af << shift);
    set_mode(port, pin, GPIO_MODE_ALTERNATE, GPIO_PULL_NONE);
}

void port_gpio_analog(gpio_regs_t *port, uint32_t pin)
{
    set_mode(port, pin, GPIO_MODE_ANALOG, GPIO_PULL_NONE);
}
