#!/usr/bin/env bash
# The lab fine-tuning demonstration's data (issue 58 part 5; docs/calibration.md, "Rendered
# stand-ins for lab runs"): the Mitsuba lab-look sequences of data/lab_demo made into lab
# recordings (video + mocap CSV, oibar_hil.lab_recording) and taken through the calibration
# toolbox as real runs would be: calibration estimated from its own recording, then per run
# extract -> apply -> to-dataset into data/lab/train (lb000-lb009) and data/lab/held (lb010,
# lb011). The fine-tune itself is `make finetune-lab`.
#
#   scripts/lab_demo.sh [NAME ...]        default: lb000 ... lb011 (each rendered to the end)
#   LAB_DEMO_SRC=data/lab_demo LAB_DIR=data/lab LAB_DEMO_SEED=1 PY=.venv/bin/python
#   LAB_SMOOTH_S=0.5: apply's local fit of the mocap, +- this many seconds (0: interpolation).
#   Chosen on the ten training runs' labels against the renderer's truth (docs/calibration.md,
#   "Labels: the mocap's noise"); the held runs were not looked at.
#
# Idempotent: a step whose output is there, and newer than what it was made from, is kept.
# Layout under LAB_DIR: recordings/<run>/ (what the lab brings home), recordings/calibration/,
# calib.json, runs/<run>/ (extracted frames and their labels), train/<run>/, held/<run>/.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PY:-.venv/bin/python}
export PYTHONPATH="hil:host${PYTHONPATH:+:$PYTHONPATH}"
SRC=${LAB_DEMO_SRC:-data/lab_demo}
LAB=${LAB_DIR:-data/lab}
SEED=${LAB_DEMO_SEED:-1}
SMOOTH=${LAB_SMOOTH_S:-0.5}
HELD=" lb010 lb011 "  # the paper's 2 held sequences; the other 10 fine-tune
REC=$LAB/recordings
RUNS=$LAB/runs
CALIB=$LAB/calib.json

say() { printf '[lab-demo] %s\n' "$*"; }
oibar() { "$PY" -c 'import sys; from oibar.cli import main; sys.exit(main())' "$@"; }
# one field of a JSON file
field() { "$PY" -c 'import json, sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$1" "$2"; }
# stdout of a step, one line, under the run's name
tag() { sed "s|^|[lab-demo] $1: |"; }

if [[ $# -gt 0 ]]; then names=("$@"); else names=(lb000 lb001 lb002 lb003 lb004 lb005 lb006 lb007 lb008 lb009 lb010 lb011); fi
dirs=()
for n in "${names[@]}"; do
    if [[ ! -f $SRC/$n/manifest.json ]]; then
        echo "error: $SRC/$n is not rendered to the end (no manifest.json): python -m oibar_hil.dataset --out $SRC --spec models/scenes/lab_demo.json" >&2
        exit 2
    fi
    dirs+=("$SRC/$n")
done
mkdir -p "$RUNS"

say "1/3 lab recordings of ${#names[@]} run(s) and the calibration recording -> $REC"
"$PY" -m oibar_hil.lab_recording "${dirs[@]}" --out "$REC" --seed "$SEED" --calibration --no-progress | tag recordings

for n in "${names[@]}"; do
    # recordings are named after the sequence's spec, which the generator names its folder after
    [[ -f $REC/$n/recording.json ]] || { echo "error: no recording $REC/$n: is $SRC/$n named after its spec?" >&2; exit 2; }
done
first=$REC/${names[0]}/recording.json
housing=$(field "$first" housing_body)
target=$(field "$first" target_body)
if [[ -f $CALIB && ! $REC/calibration/truth.json -nt $CALIB ]]; then
    say "2/3 calibration: $CALIB kept"
else
    say "2/3 calibration: oibar calib estimate on $REC/calibration -> $CALIB"
    # No --intrinsics: the lab camera is the OIBAR camera, so to-dataset copies frames as they are.
    oibar calib estimate --mocap "$REC/calibration/mocap.csv" --frames "$REC/calibration/frames.csv" \
        --pattern "$REC/calibration/pattern.json" --housing-body "$housing" --target-body "$target" \
        -o "$LAB/.calib.json.partial" >"$LAB/calib.log" 2>&1 || { cat "$LAB/calib.log" >&2; exit 2; }
    mv "$LAB/.calib.json.partial" "$CALIB"
    grep -E '^(T_|offset_s|residuals)' "$LAB/calib.log" | tag calibration
fi

say "3/3 per run: extract -> apply -> to-dataset"
for n in "${names[@]}"; do
    rec=$REC/$n
    run=$RUNS/$n
    if [[ $HELD == *" $n "* ]]; then dest=$LAB/held/$n; else dest=$LAB/train/$n; fi
    video=$rec/$(field "$rec/recording.json" video)
    if [[ -f $run/frames.csv && ! $video -nt $run/frames.csv ]]; then
        say "$n: extract: $run kept"
    else
        rm -rf "$run" "$RUNS/.$n.partial"
        oibar calib extract "$video" "$RUNS/.$n.partial" --every "$(field "$rec/recording.json" extract_every)" | tag "$n"
        mv "$RUNS/.$n.partial" "$run"
    fi
    # labels made with other apply settings are made again
    args="--smooth-half-width-s $SMOOTH"
    if [[ -f $run/poses.csv && ! $CALIB -nt $run/poses.csv && ! $run/frames.csv -nt $run/poses.csv \
          && "$(cat "$run/apply_args" 2>/dev/null)" == "$args" ]]; then
        say "$n: apply: $run/poses.csv kept"
    else
        # shellcheck disable=SC2086  # $args is two words on purpose
        oibar calib apply --calib "$CALIB" --mocap "$rec/mocap.csv" --frames "$run/frames.csv" $args \
            -o "$run/.poses.partial.csv" | tag "$n"
        mv "$run/.poses.partial.csv" "$run/poses.csv"
        echo "$args" >"$run/apply_args"
    fi
    force=()
    # new labels replace the sequence made from the old ones (to-dataset keeps one made from these)
    if [[ -f $dest/manifest.json && $run/poses.csv -nt $dest/manifest.json ]]; then force=(--force); fi
    mkdir -p "$(dirname "$dest")"
    oibar calib to-dataset "$run" --calib "$CALIB" --out "$dest" "${force[@]}" | tag "$n"
done
say "done: $(ls -d "$LAB"/train/*/ 2>/dev/null | wc -l) training and $(ls -d "$LAB"/held/*/ 2>/dev/null | wc -l) held sequence(s); next: make finetune-lab"
