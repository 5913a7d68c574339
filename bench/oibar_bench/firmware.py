"""Figure 5: the STM32F405 image's flash and RAM per module, against the build's budgets, and
the cost of the step interrupt.

Sizes come from the linker map that `make firmware-arm` writes (build/fw-arm/oibar_stm32f4.map):
every input section placed in an allocated output section, attributed to the object file it
came from, then grouped by module. The sums are checked against arm-none-eabi-size.

The step interrupt is counted two ways:
- dynamically, on this machine: bench/callgrind/step_isr.c runs the firmware's own
  oibar_stepper_isr (drv_stepper.c) N times against the unit tests' fake HAL under
  ``valgrind --tool=callgrind --toggle-collect=oibar_stepper_isr``; x86-64 instructions per
  interrupt are a proxy for Thumb-2 instructions (similar RISC-like load/compare/store code);
- statically, on the real image: the Thumb-2 instructions of TIM2_IRQHandler and of every
  function the step path calls, from arm-none-eabi-objdump. Those functions have no loops
  (checked: no backward branch), so the sum bounds what one interrupt can execute.
Either count becomes cycles with an assumed CPI for a Cortex-M4 at 168 MHz running from flash
through the ART accelerator (1.2-1.5 cycles per instruction) plus the exception entry and exit
(12 + 12 cycles, no floating-point context: the ISR uses no FPU register).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from collections import defaultdict
from pathlib import Path

from .core import BUILD, ROOT, Context, Result, Target, measurement

FW_ARM = BUILD / "fw-arm"
ELF = FW_ARM / "oibar_stm32f4.elf"
MAP = FW_ARM / "oibar_stm32f4.map"
HARNESS_SRC = ROOT / "bench" / "callgrind" / "step_isr.c"
HARNESS = BUILD / "bench" / "step_isr"

FLASH_SECTIONS = {".isr_vector", ".text", ".rodata", ".ARM.exidx", ".data"}  # .data: its initial values
RAM_SECTIONS = {".data", ".bss", ".noinit"}

CPU_HZ = 168e6
CPI_RANGE = (1.2, 1.5)  # assumed cycles per instruction, Cortex-M4 from flash with ART
EXCEPTION_CYCLES = 12 + 12  # entry (stacking) + exit (unstacking), no lazy FP context
CPU_SHARE_TARGET_PCT = 10.0
# Functions the common step path goes through on the board (hal_step.c, hal_gpio.c, drv_stepper.c).
STEP_PATH = [
    "TIM2_IRQHandler",
    "oibar_stepper_isr",
    "hal_di_read",
    "hal_step_pulse",
    "hal_step_timer_set_period",
]


# ----------------------------------------------------------------------------- linker map
def module_of(obj: str) -> str:
    """The module an object file of the map belongs to."""
    name = obj.rsplit("/", 1)[-1]
    if "liboibar_link.a" in obj:
        return "link (firmware/link)"
    if "liboibar_app.a" in obj:
        member = re.search(r"\((.+?)\.c\.obj\)", obj)
        m = member.group(1) if member else ""
        if m.startswith("drv_") or m == "pressure_loop":
            return "drivers (firmware/app/src/drv_*.c, pressure_loop.c)"
        return "application (firmware/app: state machine, safety, faults, params, events, link glue)"
    if "liboibar_proto.a" in obj:
        return "protocol descriptors (generated oibar.pb.c)"
    if "libnanopb.a" in obj:
        return "nanopb runtime"
    if "oibar_stm32f4.dir" in obj:
        if name.startswith("startup.c"):
            return "startup + C runtime (startup.c, newlib-nano, libgcc, libm)"
        return "port/stm32f4 (HAL: clock, GPIO, UART, step timers, ADC, main)"
    if re.search(r"lib(c|g|gcc|m|c_nano|g_nano|nosys)\.a|crt\w*\.o", obj):
        return "startup + C runtime (startup.c, newlib-nano, libgcc, libm)"
    return f"other ({name})"


MODULE_ORDER = [
    "link (firmware/link)",
    "application (firmware/app: state machine, safety, faults, params, events, link glue)",
    "drivers (firmware/app/src/drv_*.c, pressure_loop.c)",
    "port/stm32f4 (HAL: clock, GPIO, UART, step timers, ADC, main)",
    "nanopb runtime",
    "protocol descriptors (generated oibar.pb.c)",
    "startup + C runtime (startup.c, newlib-nano, libgcc, libm)",
    "alignment fill",
]

_OUT_SECTION = re.compile(r"^(\.[\w.]+)(?:\s+0x[0-9a-f]+\s+0x[0-9a-f]+)?")
_IN_FULL = re.compile(r"^ (\S+)\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S.*)$")
_IN_NAME = re.compile(r"^ (\.\S+|COMMON)\s*$")
_IN_CONT = re.compile(r"^\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S.*)$")
_FILL = re.compile(r"^ \*fill\*\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)")


def parse_map(path: Path) -> dict[str, dict[str, int]]:
    """{module: {"flash": bytes, "ram": bytes}} from a GNU ld map."""
    text = path.read_text(errors="replace")
    start = text.find("Linker script and memory map")
    if start < 0:
        raise RuntimeError(f"{path}: no 'Linker script and memory map' part; is it a GNU ld map?")
    sizes: dict[str, dict[str, int]] = defaultdict(lambda: {"flash": 0, "ram": 0})
    out_sec = None
    pending = None

    def add(obj_module: str, size: int) -> None:
        if out_sec in FLASH_SECTIONS:
            sizes[obj_module]["flash"] += size
        if out_sec in RAM_SECTIONS:
            sizes[obj_module]["ram"] += size

    for line in text[start:].splitlines()[1:]:
        if line and not line[0].isspace():
            m = _OUT_SECTION.match(line)
            out_sec = m.group(1) if m else None
            pending = None
            continue
        if out_sec not in FLASH_SECTIONS | RAM_SECTIONS:
            continue
        m = _FILL.match(line)
        if m:
            add("alignment fill", int(m.group(2), 16))
            continue
        m = _IN_FULL.match(line)
        if m and not m.group(4).startswith("0x"):
            add(module_of(m.group(4)), int(m.group(3), 16))
            pending = None
            continue
        m = _IN_NAME.match(line)
        if m:
            pending = m.group(1)
            continue
        m = _IN_CONT.match(line)
        if m and pending is not None:
            add(module_of(m.group(3)), int(m.group(2), 16))
            pending = None
    return dict(sizes)


def size_totals(elf: Path) -> dict[str, int]:
    """text, data, bss from arm-none-eabi-size (Berkeley), as the build's budget check reads them."""
    out = subprocess.run(
        ["arm-none-eabi-size", "-B", "-d", str(elf)], capture_output=True, text=True, check=True
    )
    m = re.search(r"^\s*(\d+)\s+(\d+)\s+(\d+)", out.stdout.splitlines()[1])
    if m is None:
        raise RuntimeError(f"cannot read arm-none-eabi-size output:\n{out.stdout}")
    text, data, bss = (int(x) for x in m.groups())
    return {"text": text, "data": data, "bss": bss, "flash": text + data, "ram": data + bss}


def budgets() -> dict[str, int]:
    """The budgets the build enforces: from the build's CMake cache, else the CMakeLists default."""
    out = {}
    sources = [FW_ARM / "CMakeCache.txt", ROOT / "firmware" / "port" / "stm32f4" / "CMakeLists.txt"]
    for key, name in (("flash", "OIBAR_FLASH_BUDGET_BYTES"), ("ram", "OIBAR_RAM_BUDGET_BYTES")):
        for src in sources:
            if src.is_file():
                m = re.search(rf"{name}(?::STRING=|\s+)(\d+)", src.read_text())
                if m:
                    out[key] = int(m.group(1))
                    break
        if key not in out:
            raise RuntimeError(f"{name} found in neither {sources[0]} nor {sources[1]}")
    return out


SIZE_COLUMNS = [
    ("module", "module"),
    ("flash_B", "flash (bytes)"),
    ("flash_share", "share of image flash (%)"),
    ("ram_B", "static RAM (bytes)"),
    ("ram_share", "share of static RAM (%)"),
]


def _need_image() -> None:
    for p in (ELF, MAP):
        if not p.is_file():
            raise FileNotFoundError(f"{p.relative_to(ROOT)} is missing: run `make firmware-arm` first")
    if shutil.which("arm-none-eabi-size") is None:
        raise FileNotFoundError("arm-none-eabi-size not installed: run `make setup` (gcc-arm-none-eabi)")


@measurement(
    "firmware.modules", "Flash and static RAM per module (STM32F405 image, MinSizeRel)", SIZE_COLUMNS
)
def modules(ctx: Context) -> Result:
    _need_image()
    sizes = parse_map(MAP)
    tot = size_totals(ELF)
    flash_sum = sum(v["flash"] for v in sizes.values())
    ram_sum = sum(v["ram"] for v in sizes.values())
    order = MODULE_ORDER + sorted(k for k in sizes if k not in MODULE_ORDER)
    rows = []
    for mod in order:
        if mod not in sizes:
            continue
        v = sizes[mod]
        if v["flash"] == 0 and v["ram"] == 0:
            continue  # e.g. the linker's empty stub sections
        rows.append(
            {
                "module": mod,
                "flash_B": v["flash"],
                "flash_share": 100.0 * v["flash"] / flash_sum,
                "ram_B": v["ram"],
                "ram_share": 100.0 * v["ram"] / ram_sum if ram_sum else 0.0,
            }
        )
    rows.append(
        {
            "module": "**total**",
            "flash_B": flash_sum,
            "flash_share": 100.0,
            "ram_B": ram_sum,
            "ram_share": 100.0,
        }
    )
    notes = [
        f"From {MAP.relative_to(ROOT)}: every input section of .isr_vector, .text (with .rodata), "
        ".ARM.exidx and .data (flash holds its initial values) and of .data, .bss, .noinit (RAM), by object "
        "file. The port's main.c holds the link instance (its buffers) in its .bss."
    ]
    if (flash_sum, ram_sum) == (tot["flash"], tot["ram"]):
        notes.append(
            f"The sums equal arm-none-eabi-size: flash {tot['flash']:,} (text {tot['text']:,} + data "
            f"{tot['data']:,}), RAM {tot['ram']:,} (data {tot['data']:,} + bss {tot['bss']:,})."
        )
    else:
        notes.append(
            f"**Check**: the map sums (flash {flash_sum:,}, RAM {ram_sum:,}) differ from "
            f"arm-none-eabi-size (flash {tot['flash']:,}, RAM {tot['ram']:,})."
        )
    ctx.progress(f"firmware modules: flash {flash_sum:,} B, RAM {ram_sum:,} B over {len(rows) - 1} modules")
    return Result(rows, notes)


BUDGET_COLUMNS = [
    ("what", "image"),
    ("bytes", "bytes"),
    ("budget_B", "budget (bytes)"),
    ("used_pct", "used (%)"),
    ("target", "target"),
    ("gap", "gap"),
]


@measurement("firmware.budget", "Totals against the budgets the build enforces", BUDGET_COLUMNS)
def budget(ctx: Context) -> Result:
    _need_image()
    tot = size_totals(ELF)
    b = budgets()
    rows = []
    for key, what in (
        ("flash", "flash (text + data)"),
        ("ram", "static RAM (data + bss, stack not included)"),
    ):
        t = Target(
            "<=", float(b[key]), "B", "firmware/port/stm32f4/CMakeLists.txt (the build fails above it)"
        )
        rows.append(
            {
                "what": what,
                "bytes": tot[key],
                "budget_B": b[key],
                "used_pct": 100.0 * tot[key] / b[key],
                "target": t,
                "measured": float(tot[key]),
            }
        )
    return Result(
        rows,
        [
            "The STM32F405 has 1 MiB of flash and 128 KiB of SRAM; the budgets are the project's. "
            "The linker script keeps at least 8 KiB below the top of RAM for the main stack."
        ],
    )


# ----------------------------------------------------------------------------- step interrupt
def build_harness() -> Path:
    """Compile bench/callgrind/step_isr.c with the firmware's sources (optimised like the image,
    no sanitizers: they would multiply the instruction count)."""
    gen = Path(os.environ.get("OIBAR_GEN_C", BUILD / "gen" / "c"))
    nanopb = Path(os.environ.get("OIBAR_NANOPB_DIR", ROOT / ".cache" / "src" / "nanopb"))
    for p, how in ((gen / "oibar.pb.c", "make gen"), (nanopb / "pb_encode.c", "make setup")):
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: run `{how}`")
    srcs = [
        HARNESS_SRC,
        *sorted((ROOT / "firmware" / "link" / "src").glob("*.c")),
        *sorted((ROOT / "firmware" / "app" / "src").glob("*.c")),
        ROOT / "tests" / "firmware" / "support" / "fake_hal.c",
        nanopb / "pb_common.c",
        nanopb / "pb_encode.c",
        nanopb / "pb_decode.c",
        gen / "oibar.pb.c",
    ]
    HARNESS.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        "gcc",
        "-std=c11",
        "-Os",
        "-DNDEBUG",
        "-g",
        "-Wall",
        "-Wextra",
        *[
            f"-I{ROOT / d}"
            for d in (
                "firmware/link/include",
                "firmware/app/include",
                "firmware/hal/include",
                "tests/firmware/support",
            )
        ],
        "-isystem",
        str(gen),
        "-isystem",
        str(nanopb),
        "-o",
        str(HARNESS),
        *map(str, srcs),
        "-lm",
    ]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"building the step-ISR harness failed:\n{p.stderr[-3000:]}")
    return HARNESS


def callgrind_count(harness: Path, mode: str, n: int, tmp: Path) -> tuple[int, dict]:
    """(instructions inside oibar_stepper_isr over n interrupts, the harness's JSON line)."""
    out_file = tmp / f"callgrind.{mode}.out"
    cmd = [
        "valgrind",
        "--tool=callgrind",
        "--toggle-collect=oibar_stepper_isr",
        f"--callgrind-out-file={out_file}",
        str(harness),
        mode,
        str(n),
    ]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {p.returncode}):\n{(p.stdout + p.stderr)[-2000:]}")
    info = json.loads(p.stdout.strip().splitlines()[-1])
    m = re.search(r"^(?:summary|totals):\s*(\d+)", out_file.read_text(), re.M)
    if m is None:
        raise RuntimeError(f"no totals in {out_file}")
    return int(m.group(1)), info


_FUNC = re.compile(r"^([0-9a-f]+) <([^>]+)>:$")
_INSN = re.compile(r"^\s+([0-9a-f]+):\s+(\S+)\s*(.*)$")
_TARGET = re.compile(r"\b([0-9a-f]+) <([^>+]+)(\+0x[0-9a-f]+)?>")
_COND = "(eq|ne|cs|cc|hs|lo|mi|pl|vs|vc|hi|ls|ge|lt|gt|le)"
_B_UNCOND = re.compile(r"^b(\.[nw])?$")
_B_COND = re.compile(rf"^(b{_COND}(\.[nw])?|cbn?z)$")
_RETURN = re.compile(r"^(bx(\.n)?|pop(\.w)?|ldmia(\.w)?|ldm(\.w)?|ldmfd(\.w)?)$")


def arm_functions(elf: Path) -> dict[str, list[tuple[int, str, str]]]:
    """Thumb-2 functions of the image: name -> [(address, mnemonic, operands)], literals left out."""
    out = subprocess.run(
        ["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(elf)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    funcs: dict[str, list] = {}
    cur = None
    for line in out.splitlines():
        m = _FUNC.match(line)
        if m:
            cur = funcs.setdefault(m.group(2), [])
            continue
        m = _INSN.match(line)
        if cur is not None and m and not m.group(2).startswith("."):  # .word/.short: literal pool
            cur.append((int(m.group(1), 16), m.group(2), m.group(3)))
    return funcs


def longest_path(name: str, insns: list[tuple[int, str, str]]) -> int:
    """Most instructions one call of the function can execute (callees not included), from its
    control-flow graph; raises if the graph has a cycle (a loop: no static bound) or a jump
    table this reader does not follow."""
    index = {a: i for i, (a, _, _) in enumerate(insns)}
    succ: list[list[int]] = []
    for i, (addr, mn, ops) in enumerate(insns):
        nxt = [i + 1] if i + 1 < len(insns) else []
        t = _TARGET.search(ops)
        intra = t is not None and (t.group(2) == name) and int(t.group(1), 16) in index
        if mn.startswith(("tbb", "tbh")):
            raise ValueError(f"{name}: jump table at {addr:#x}")
        if _B_UNCOND.match(mn):
            succ.append([index[int(t.group(1), 16)]] if intra else [])  # else a tail call
        elif _B_COND.match(mn):
            succ.append(nxt + ([index[int(t.group(1), 16)]] if intra else []))
        elif _RETURN.match(mn) and (mn.startswith("bx") or "pc" in ops):
            succ.append([])  # return / indirect tail call
        else:
            succ.append(nxt)  # incl. bl/blx (calls return)
    memo: dict[int, int] = {}
    on_stack: set[int] = set()

    def walk(i: int) -> int:
        if i in memo:
            return memo[i]
        if i in on_stack:
            raise ValueError(f"{name}: loop at {insns[i][0]:#x}, no static bound")
        on_stack.add(i)
        memo[i] = 1 + max((walk(j) for j in succ[i]), default=0)
        on_stack.discard(i)
        return memo[i]

    return walk(0)


ISR_COLUMNS = [
    ("path", "interrupt path"),
    ("basis", "counted"),
    ("insns", "instructions / interrupt"),
    ("cycles", "cycles (CPI 1.2-1.5 + 24)"),
    ("us", "µs at 168 MHz"),
    ("cpu_default", "CPU at the default speed (%)"),
    ("cpu_max", "CPU at the highest settable speed (%)"),
    ("max_rate", "max steps/s under 10 % CPU"),
    ("target", "target"),
    ("gap", "gap"),
]


def _isr_row(path: str, basis: str, insns: float, rates: dict) -> dict:
    lo = insns * CPI_RANGE[0] + EXCEPTION_CYCLES
    hi = insns * CPI_RANGE[1] + EXCEPTION_CYCLES
    cpu_max = 100.0 * rates["max"] * hi / CPU_HZ
    t = Target(
        "<=",
        CPU_SHARE_TARGET_PCT,
        "% CPU",
        f"issue 10, at the fastest rate the parameters allow ({rates['max']:.0f} steps/s)",
    )
    return {
        "path": path,
        "basis": basis,
        "insns": insns,
        "cycles": f"{lo:.0f}-{hi:.0f}",
        "cycles_hi": hi,
        "us": f"{lo / CPU_HZ * 1e6:.2f}-{hi / CPU_HZ * 1e6:.2f}",
        "cpu_default": 100.0 * rates["default"] * hi / CPU_HZ,
        "cpu_max": cpu_max,
        "max_rate": int(CPU_SHARE_TARGET_PCT / 100.0 * CPU_HZ / hi),
        "target": t,
        "measured": cpu_max,
    }


@measurement("firmware.step_isr", "Step interrupt cost (oibar_stepper_isr)", ISR_COLUMNS)
def step_isr(ctx: Context) -> Result:
    if shutil.which("valgrind") is None:
        raise FileNotFoundError(
            "valgrind is not installed (Debian package `valgrind`): the step-ISR count needs callgrind"
        )
    n = 20000 if ctx.quick else 200000
    n_finish = 2000 if ctx.quick else 20000
    ctx.progress("firmware step ISR: building the harness (gcc -Os, no sanitizers)")
    harness = build_harness()
    ctx.progress(f"firmware step ISR: callgrind, {n:,} steps and {n_finish:,} move ends")
    ir_step, info = callgrind_count(harness, "step", n, ctx.tmp)
    ir_finish, _ = callgrind_count(harness, "finish", n_finish, ctx.tmp)
    rates = {"default": info["latch_max_speed_steps_s"], "max": info["latch_max_speed_steps_s_max"]}
    per_step, per_finish = ir_step / info["calls"], ir_finish / n_finish

    # The port's TIM2_IRQHandler (clear the flag, call through the pointer) runs before the ISR on
    # the board; its Thumb-2 count is added to the x86 one. Then the static bound on the image.
    wrapper, bound_row, notes = 0, None, []
    if ELF.is_file() and shutil.which("arm-none-eabi-objdump"):
        funcs = arm_functions(ELF)
        try:
            longest = {f: longest_path(f, funcs[f]) for f in STEP_PATH}
        except (KeyError, ValueError) as exc:
            notes.append(f"ARM static bound not computed: {exc}.")
        else:
            wrapper = longest["TIM2_IRQHandler"]
            basis = "Thumb-2, static longest path: " + " + ".join(f"{f} {longest[f]}" for f in STEP_PATH)
            bound_row = {
                **_isr_row("step (common path), upper bound", basis, float(sum(longest.values())), rates),
                "x86": False,
            }
            notes.append(
                "ARM static bound: the longest path through each function's control-flow graph in the "
                "image (no loops: checked), summed over the functions the step path calls, each once."
            )
    plus = f" + TIM2_IRQHandler {wrapper} (Thumb-2)" if wrapper else ""
    rows = [
        {
            **_isr_row(
                "step (common path)",
                f"x86-64 callgrind, mean over {info['calls']:,}{plus}",
                per_step + wrapper,
                rates,
            ),
            "ir_total": ir_step,
            "ir_per_call": per_step,
            "x86": True,
        },
        {
            **_isr_row(
                "end of move (switch reached, event posted)",
                f"x86-64 callgrind, mean over {n_finish:,}{plus}",
                per_finish + wrapper,
                rates,
            ),
            "ir_total": ir_finish,
            "ir_per_call": per_finish,
            "x86": True,
        },
    ]
    if bound_row:
        rows.append(bound_row)
    notes[:0] = [
        f"Cycles = instructions x CPI + {EXCEPTION_CYCLES} (exception entry and exit), with an assumed CPI of "
        f"{CPI_RANGE[0]}-{CPI_RANGE[1]} for a Cortex-M4 at 168 MHz executing from flash through the ART "
        "accelerator; the CPU shares and the rate use the pessimistic end. x86-64 instruction counts stand in "
        "for Thumb-2 ones: a proxy, not a measurement on the board.",
        f"Step rates: latch_max_speed_steps_s is {rates['default']:.0f} by default and at most "
        f"{rates['max']:.0f} (firmware/app/src/params.c); the target applies at the maximum. The ramp table "
        f"has {info['ramp_entries']} entries at the default speed and acceleration.",
        f"Harness: {HARNESS_SRC.relative_to(ROOT)} + firmware/app, firmware/link, tests/firmware/support/fake_hal.c, "
        "compiled -Os like the image, without sanitizers.",
    ]
    ctx.progress(
        f"firmware step ISR: {per_step:.1f} x86 instructions per step, {per_finish:.1f} per move end"
    )
    return Result(rows, notes)
