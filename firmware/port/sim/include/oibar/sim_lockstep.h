/*
 * Lockstep protocol between the HIL rig's plant (Python, hil/oibar_hil/rig)
 * and the simulated MCU (PX4/ArduPilot SITL pattern, docs/hil.md).
 *
 * One exchange = one plant message, then one MCU reply, over a SOCK_SEQPACKET
 * Unix socket. The plant message carries the sensor inputs and how much
 * simulated time to run; the MCU runs exactly that many 1 ms ticks with those
 * inputs and replies with its actuator outputs. Frames are numbered 1, 2, ...:
 * the MCU refuses any frame that is not the next one (a lost or repeated
 * exchange), and the plant checks the echo and the cumulative step count.
 *
 * Both messages are little-endian u32/u16 fields, packed in the order below
 * (the Python side mirrors them with struct formats; keep both in step).
 */
#ifndef OIBAR_SIM_LOCKSTEP_H
#define OIBAR_SIM_LOCKSTEP_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define SIM_LS_PLANT_MAGIC 0x5053424Fu /* "OBSP" */
#define SIM_LS_MCU_MAGIC 0x4D53424Fu   /* "OBSM" */
#define SIM_LS_VERSION 1u
#define SIM_LS_ADC_SLOTS 8u
#define SIM_LS_MAX_ADVANCE_MS 100u

/* plant -> MCU flags */
#define SIM_LS_FLAG_HANG_MAIN_LOOP 0x1u /* main loop stops until the next reset */
#define SIM_LS_FLAG_QUIT 0x2u           /* reply once, then exit */
#define SIM_LS_FLAG_RESET_PIN 0x4u      /* the reset pin pulled (brown-out, a restart): boot again before this exchange runs */

/* MCU -> plant status */
enum {
    SIM_LS_OK = 0,
    SIM_LS_ERR_FRAME = 1,   /* not the next frame: lost or repeated exchange */
    SIM_LS_ERR_MAGIC = 2,
    SIM_LS_ERR_ADVANCE = 3, /* advance_ms outside 1..SIM_LS_MAX_ADVANCE_MS */
    SIM_LS_ERR_SIZE = 4
};

/* MCU -> plant flags */
#define SIM_LS_MCU_STEP_TIMER_RUNNING 0x1u
#define SIM_LS_MCU_MAIN_HUNG 0x2u

typedef struct {
    uint32_t magic;
    uint32_t version;
    uint32_t frame;          /* 1, 2, 3, ... */
    uint32_t advance_ms;     /* simulated time this exchange covers */
    uint32_t flags;          /* SIM_LS_FLAG_* */
    uint32_t di_bits;        /* bit i = hal_di_t i holds */
    uint32_t adc_fail_bits;  /* bit i = conversion of hal_adc_t i failed */
    uint32_t uart_rx_bytes;  /* bytes the host wrote to the pty since the last exchange */
    uint16_t adc_counts[SIM_LS_ADC_SLOTS];
} sim_ls_plant_t;

typedef struct {
    uint32_t magic;
    uint32_t version;
    uint32_t frame;           /* echo of the plant frame */
    uint32_t status;          /* SIM_LS_OK or SIM_LS_ERR_* */
    uint32_t expected_frame;  /* the frame the MCU wanted */
    uint32_t sim_time_ms;     /* simulated time since the process started */
    uint32_t uptime_ms;       /* hal_time_ms(): since the last reset */
    uint32_t do_bits;         /* outputs at the end of the exchange */
    uint32_t do_any_bits;     /* outputs energised at any tick of the exchange */
    uint32_t steps_fwd;       /* step pulses with DIR = towards release, this exchange */
    uint32_t steps_rev;       /* step pulses with DIR = towards home, this exchange */
    uint32_t steps_total;     /* all step pulses since the process started */
    uint32_t uart_tx_bytes;   /* bytes written to the pty during this exchange */
    uint32_t uart_rx_pending; /* host bytes received but not yet clocked into the UART */
    uint32_t resets;          /* resets since the process started */
    uint32_t reset_cause;     /* hal_reset_cause_t of the latest (re)start */
    uint32_t watchdog_kicks;  /* since the process started */
    uint32_t flags;           /* SIM_LS_MCU_* */
    uint32_t app_state;       /* oibar_v1_State, for the rig's ground-truth checks */
    uint32_t valve_violation_ms; /* ms with a valve coil on outside STATE_TRANSFERRING */
    uint32_t fault_flags;     /* latched faults, bit (FaultCode - 1), at the end of the exchange */
} sim_ls_mcu_t;

#define SIM_LS_PLANT_BYTES (8u * 4u + SIM_LS_ADC_SLOTS * 2u)
#define SIM_LS_MCU_BYTES (21u * 4u)

/* Encode/decode in the packed little-endian layout. Decode returns false on a
 * wrong length. */
size_t sim_ls_encode_plant(const sim_ls_plant_t *m, uint8_t *buf, size_t cap);
bool sim_ls_decode_plant(const uint8_t *buf, size_t len, sim_ls_plant_t *m);
size_t sim_ls_encode_mcu(const sim_ls_mcu_t *m, uint8_t *buf, size_t cap);
bool sim_ls_decode_mcu(const uint8_t *buf, size_t len, sim_ls_mcu_t *m);

#endif /* OIBAR_SIM_LOCKSTEP_H */
