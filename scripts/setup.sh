#!/usr/bin/env bash
# One-shot, idempotent set-up of everything OIBAR needs on Debian 12:
#   1. missing Debian packages (installed when root, otherwise the exact command is printed);
#   2. the Python virtual environment (.venv) with the pinned requirements of one set-up profile
#      (requirements/profiles.conf: flight, demo, train or test);
#   3. the Unity and nanopb C sources, from Debian source packages, checksummed (.cache/src).
# When everything is already there it only checks, in well under 10 s.
#
# Environment:
#   PYTHON=/path/to/python3   interpreter for the venv (default /usr/bin/python3)
#   SETUP_PROFILE=NAME        the Python packages: firmware (none: no .venv), flight (host only),
#                             demo or sim (the simulated rig, no torch), train, test (everything,
#                             the default); a venv set up
#                             for a larger profile serves the smaller ones as it is
#   UNITY_DIR=/path           use these Unity sources instead of fetching them
#   NANOPB_DIR=/path          use these nanopb runtime sources instead of fetching them
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
CACHE="$ROOT/.cache"
VENV="$ROOT/.venv"
PYTHON=${PYTHON:-/usr/bin/python3}
PROFILE=${SETUP_PROFILE:-test}
[ "$PROFILE" = sim ] && PROFILE=demo
PROFILES=requirements/profiles.conf

say()  { printf 'setup: %s\n' "$*"; }
die()  { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

# --- 1. Debian packages -------------------------------------------------------------------
apt_packages() {
  local wanted missing=()
  wanted=$(sed -e 's/#.*//' -e '/^[[:space:]]*$/d' scripts/apt-packages.txt)
  for p in $wanted; do
    dpkg-query -W -f='${db:Status-Abbrev}' "$p" 2>/dev/null | grep -q '^ii' || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  local cmd="apt-get install -y --no-install-recommends ${missing[*]}"
  if [ "$(id -u)" -ne 0 ]; then
    die "missing Debian packages: ${missing[*]}
  run as root:  sudo apt-get update && sudo $cmd
  then run this again."
  fi
  say "installing Debian packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  # A fresh machine may have empty package lists; refresh once if the install cannot find them.
  if ! $cmd >/dev/null 2>"$CACHE/apt-install.log"; then
    apt-get update -q >/dev/null
    $cmd >/dev/null 2>"$CACHE/apt-install.log" || die "apt-get failed, see $CACHE/apt-install.log"
  fi
}

# --- 2. Python virtual environment -------------------------------------------------------
# The profile's line of requirements/profiles.conf: "<files> | <packages>".
profile_spec() {
  sed -e 's/#.*//' "$PROFILES" | awk -F: -v p="$1" '$1 == p { sub(/^[^:]*:/, ""); print; exit }'
}
profile_files() { local s; s=$(profile_spec "$1"); echo ${s%%|*}; }
profile_pkgs()  { local s; s=$(profile_spec "$1"); echo ${s#*|}; }
all_profiles()  { sed -e 's/#.*//' "$PROFILES" | awk -F: 'NF > 1 { print $1 }'; }
# A profile's stamp: its name, its pins and the definitions of the packages it installs.
profile_hash() {
  local f paths=()
  for f in $(profile_files "$1"); do paths+=("requirements/$f.txt"); done
  for f in $(profile_pkgs "$1"); do paths+=("$f/pyproject.toml"); done
  { echo "$1"; [ ${#paths[@]} -eq 0 ] || cat "${paths[@]}"; } | sha256sum | cut -c1-16
}
# True when every word of $1 is among the words of $2.
words_within() { local w; for w in $1; do [[ " $2 " == *" $w "* ]] || return 1; done; }

# PyTorch's Linux wheels on PyPI come with the CUDA libraries (PyPI has no CPU-only build): of
# the 7.1 GB the full venv takes, 6 GB are torch, triton and nvidia-*; only the train and test
# profiles install them. Installed in one pip call, pip keeps every downloaded wheel beside the
# unpacked files until the end: a measured peak of 11.1 GB. So we resolve first (metadata only),
# then install the big wheels one at a time, then the rest; never into pip's cache, and with
# pip's scratch space on the venv's own disk. Without torch (flight, demo) the venv stays under
# 1 GB.
if [[ " $(profile_files "$PROFILE" 2>/dev/null) " == *" ml "* ]]; then
  PIP_NEED_MB=${PIP_NEED_MB:-8000}   # measured peak of the staged install (7.35 GB), plus a margin
else
  PIP_NEED_MB=${PIP_NEED_MB:-1500}
fi

pip_q() { "$VENV/bin/pip" install -q --disable-pip-version-check --no-cache-dir "$@"; }

# Dies, installing nothing, unless PIP_NEED_MB are free on the disk that holds .venv and pip's
# scratch space.
need_disk_for_packages() {
  local free_mb
  mkdir -p "$CACHE"
  free_mb=$(df --output=avail -B1M "$CACHE" | tail -1 | tr -d ' ')
  if [ "$free_mb" -lt "$PIP_NEED_MB" ]; then
    die "the Python packages of the $PROFILE profile need about $((PIP_NEED_MB / 1000)).$(( (PIP_NEED_MB % 1000) / 100 )) GB free on the disk of $ROOT
  while they install, but only $((free_mb / 1000)).$(( (free_mb % 1000) / 100 )) GB are free.
  Free some space and run this again; nothing was installed."
  fi
}

pip_install_staged() {
  local plan="$CACHE/pip-plan.json" tmp="$CACHE/pip-tmp"
  # A venv without torch gets the big wheels (train, test): check the disk before pip fetches
  # anything (the resolve alone fails on a full disk, with an error that says nothing of space).
  if [ "$PIP_NEED_MB" -gt 1500 ]; then
    "$VENV/bin/python" -c "import torch" >/dev/null 2>&1 || need_disk_for_packages
  else
    need_disk_for_packages
  fi
  rm -rf "$tmp" && mkdir -p "$tmp"
  say "resolving the pinned Python packages of the $PROFILE profile ($(profile_files "$PROFILE"))"
  TMPDIR="$tmp" pip_q --dry-run --report "$plan" "$@" \
    || die "pip could not resolve the requirement files (see the messages above)"
  local big=() line
  while read -r line; do big+=("$line"); done < <("$VENV/bin/python" - "$plan" <<'PY'
import json, sys
plan = json.load(open(sys.argv[1]))["install"]
heavy = [(m["name"].lower(), m["version"]) for m in (p["metadata"] for p in plan)
         if m["name"].lower().startswith("nvidia-") or m["name"].lower() in ("triton", "torch")]
# torch last: it is the one that depends on the others.
for name, ver in sorted(heavy, key=lambda nv: (nv[0] == "torch", nv[0])):
    print(f"{name}=={ver}")
PY
)
  if [ ${#big[@]} -gt 0 ]; then need_disk_for_packages; fi
  local i=0 n=$(( ${#big[@]} + 1 ))
  for line in "${big[@]}"; do
    i=$((i + 1))
    say "installing Python packages $i/$n: $line"
    TMPDIR="$tmp" pip_q --no-deps "$line" || die "pip could not install $line (see the messages above)"
  done
  say "installing Python packages $n/$n: the rest of the $PROFILE profile"
  TMPDIR="$tmp" pip_q "$@" || die "pip install failed (see the messages above)"
  rm -rf "$tmp" "$plan"
}

venv() {
  local stamp want reqs=() pkgs=() f q
  [ -n "$(profile_spec "$PROFILE")" ] \
    || die "unknown SETUP_PROFILE '$PROFILE' (one of: $(all_profiles | tr '\n' ' ')sim)"
  # A profile without Python packages (firmware) needs no venv: none is made, none is touched.
  if [ -z "$(profile_files "$PROFILE")" ] && [ -z "$(profile_pkgs "$PROFILE")" ]; then return 0; fi
  for f in $(profile_files "$PROFILE"); do
    [ -f "requirements/$f.txt" ] || die "$PROFILES names requirements/$f.txt, which does not exist"
    reqs+=(-r "requirements/$f.txt")
  done
  # Reinstall when a pin or a package definition of this profile changed. The stamp holds one
  # line per profile the venv serves: "<profile> <hash>".
  stamp="$VENV/.oibar-stamp"
  want="$PROFILE $(profile_hash "$PROFILE")"
  if [ -x "$VENV/bin/python" ] && [ -f "$stamp" ] && grep -qxF "$want" "$stamp"; then return 0; fi
  [ -x "$PYTHON" ] || die "no Python at $PYTHON (set PYTHON=/path/to/python3)"
  if [ ! -x "$VENV/bin/python" ]; then
    say "creating the virtual environment in .venv"
    "$PYTHON" -m venv "$VENV" || die "could not create .venv (is python3-venv installed?)"
  fi
  pip_install_staged "${reqs[@]}"
  # Our own packages, editable, without touching the pins.
  for f in $(profile_pkgs "$PROFILE"); do
    [ -f "$f/pyproject.toml" ] && pkgs+=(-e "$f")
  done
  if [ ${#pkgs[@]} -gt 0 ]; then
    pip_q --no-deps --no-build-isolation "${pkgs[@]}" \
      || die "installing the project's packages into .venv failed"
  fi
  # The venv now serves this profile, every profile it contains, and those it served before
  # whose pins did not change.
  local line
  for q in $(all_profiles); do
    line="$q $(profile_hash "$q")"
    if { words_within "$(profile_files "$q")" "$(profile_files "$PROFILE")" \
         && words_within "$(profile_pkgs "$q")" "$(profile_pkgs "$PROFILE")"; } \
       || { [ -f "$stamp" ] && grep -qxF "$line" "$stamp"; }; then
      echo "$line"
    fi
  done > "$stamp.new"
  mv "$stamp.new" "$stamp"
}

# --- 3. third-party C sources from Debian source packages --------------------------------
# Private apt configuration: the system's own Debian mirrors, as deb-src, in .cache/apt.
# No system file is changed.
apt_src() {
  local a="$CACHE/apt"
  mkdir -p "$a/lists/partial" "$a/cache/archives/partial" "$a/sources.d"
  if [ ! -s "$a/sources.d/debian-src.sources" ]; then
    local found=0
    for f in /etc/apt/sources.list.d/*.sources; do
      [ -f "$f" ] || continue
      grep -qi '^URIs:.*debian' "$f" || continue
      sed -e 's/^Types:.*/Types: deb-src/' "$f" >> "$a/sources.d/debian-src.sources"
      echo >> "$a/sources.d/debian-src.sources"
      found=1
    done
    if [ $found -eq 0 ] && [ -f /etc/apt/sources.list ]; then
      grep -E '^deb ' /etc/apt/sources.list | sed 's/^deb /deb-src /' > "$a/sources.d/debian-src.list"
      [ -s "$a/sources.d/debian-src.list" ] && found=1
    fi
    [ $found -eq 1 ] || die "no Debian apt source found in /etc/apt to derive deb-src entries from"
  fi
  APT_OPTS=(-o "Dir::Etc::SourceList=/dev/null" -o "Dir::Etc::SourceParts=$a/sources.d"
            -o "Dir::State::Lists=$a/lists" -o "Dir::Cache=$a/cache")
  # Our private folders belong to the invoking user; apt's '_apt' sandbox user cannot write them.
  [ "$(id -u)" -eq 0 ] && APT_OPTS+=(-o "APT::Sandbox::User=root")
  if [ ! -f "$a/lists/.updated" ]; then
    say "reading Debian source package lists"
    apt-get -q "${APT_OPTS[@]}" update >/dev/null || die "apt-get update for source lists failed"
    touch "$a/lists/.updated"
  fi
}

# Verify the files of one cache folder against scripts/third_party.lock; prints bad files.
check_folder() {
  local folder=$1 dir=$2 bad=0
  while read -r f pkg path sum; do
    [ "$f" = "$folder" ] || continue
    local file="$dir/$(basename "$path")"
    if [ ! -f "$file" ] || [ "$(sha256sum "$file" | cut -d' ' -f1)" != "$sum" ]; then
      echo "$file"; bad=1
    fi
  done < <(sed -e 's/#.*//' -e '/^[[:space:]]*$/d' scripts/third_party.lock)
  return $bad
}

fetch_folder() {
  local folder=$1 dir="$CACHE/src/$1" pkg
  check_folder "$folder" "$dir" >/dev/null && return 0
  pkg=$(awk -v f="$folder" '$1==f {print $2; exit}' <(sed 's/#.*//' scripts/third_party.lock))
  say "fetching $folder sources from Debian source package '$pkg'"
  apt_src
  local dl="$CACHE/apt/dl"
  rm -rf "$dl" && mkdir -p "$dl"
  (cd "$dl" && apt-get -q "${APT_OPTS[@]}" source --download-only "$pkg" >/dev/null 2>&1) \
    || die "could not download the source package '$pkg' (apt-get source --download-only)"
  local orig
  orig=$(ls "$dl"/"${pkg}"_*.orig.tar.* 2>/dev/null | awk 'NR==1')
  [ -n "$orig" ] || die "source package '$pkg' has no orig tarball"
  rm -rf "$dir" && mkdir -p "$dir"
  local top
  top=$(tar tf "$orig" | awk -F/ 'NR==1 {print $1}')
  while read -r f p path sum; do
    [ "$f" = "$folder" ] || continue
    tar xf "$orig" -C "$dl" "$top/$path" || die "'$path' not found in $orig"
    cp "$dl/$top/$path" "$dir/"
  done < <(sed -e 's/#.*//' -e '/^[[:space:]]*$/d' scripts/third_party.lock)
  local bad
  if ! bad=$(check_folder "$folder" "$dir"); then
    die "checksum mismatch for: $bad
  Debian's '$pkg' sources differ from scripts/third_party.lock; review them before updating the lock."
  fi
  rm -rf "$dl"
}

third_party() {
  if [ -n "${UNITY_DIR:-}" ]; then
    [ -f "$UNITY_DIR/unity.c" ] || die "UNITY_DIR=$UNITY_DIR has no unity.c"
  else
    fetch_folder unity
  fi
  if [ -n "${NANOPB_DIR:-}" ]; then
    [ -f "$NANOPB_DIR/pb_decode.c" ] || die "NANOPB_DIR=$NANOPB_DIR has no pb_decode.c"
  else
    fetch_folder nanopb
  fi
  # The generated C code must come from the same nanopb version as the runtime.
  local gen_v rt_v
  gen_v=$(nanopb_generator.py --version 2>/dev/null | tr -d '[:space:]')
  rt_v=$(sed -n 's/^#define NANOPB_VERSION *"\?\([^" ]*\)"\?.*/\1/p' "${NANOPB_DIR:-$CACHE/src/nanopb}/pb.h")
  [ "$gen_v" = "$rt_v" ] || die "nanopb generator ($gen_v) and runtime ($rt_v) differ"
  # The Python code must come from the protoc matching the pinned protobuf runtime.
  local protoc_v
  protoc_v=$(protoc --version | awk '{print $2}')
  grep -q "^protobuf==4\.${protoc_v#3.}\$" requirements/base.txt \
    || die "protoc $protoc_v does not match the protobuf runtime pinned in requirements/base.txt"
}

mkdir -p "$CACHE"
apt_packages
venv
third_party
