# Sourced by scripts/demo and scripts/test: make ./.venv exist and hold the project.
# Works on a fresh Debian machine with only python3: installs python3-venv when missing.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${CANERGY_VENV:-$ROOT/.venv}"
EXTRAS="${1:-}"

apt_install() {
    local sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    DEBIAN_FRONTEND=noninteractive $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" >/dev/null
}

# need_commands CMD:PACKAGE...: apt-install the packages of the commands that are missing
need_commands() {
    local missing=() pair
    for pair in "$@"; do
        command -v "${pair%%:*}" >/dev/null || missing+=("${pair#*:}")
    done
    [ ${#missing[@]} -eq 0 ] || apt_install "${missing[@]}"
}

# run_on_vcan SECONDS CMD...: CMD, in the current directory, where vcan0 and vcan1 are up: this
# kernel's when it has them, otherwise inside user-mode Linux (scripts/uml-run, DEVELOPERS.md),
# which it then gets SECONDS to finish in
run_on_vcan() {
    local seconds=$1
    shift
    if [ -e /sys/class/net/vcan0 ] && [ -e /sys/class/net/vcan1 ]; then
        "$@"
        return
    fi
    need_commands linux.uml:user-mode-linux insmod:kmod pgrep:procps ip:iproute2
    if [ "${UML_RUN_XSTATE_SHIM:-auto}" = 1 ] || grep -qw amx_tile /proc/cpuinfo; then
        # on an AMX CPU uml-run builds a small ptrace shim for linux.uml 6.1 (DEVELOPERS.md)
        need_commands cc:gcc
        [ -e /usr/include/stdio.h ] || apt_install libc6-dev
    fi
    echo "$(basename "$0"): no vcan0/vcan1 on this kernel; running in user-mode Linux (limit ${seconds} s)" >&2
    "$ROOT/scripts/uml-run" --timeout "$seconds" --vcan vcan0 --vcan vcan1 -- "$@"
}

if ! command -v python3 >/dev/null; then
    apt_install python3
fi
if [ ! -x "$VENV/bin/python" ]; then
    if ! python3 -m venv "$VENV" 2>/dev/null; then
        rm -rf "$VENV"
        apt_install python3-venv
        python3 -m venv "$VENV"
    fi
fi
stamp="$VENV/.canergy-installed$EXTRAS"
if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    # the build backend's warnings (setuptools' "Editable installation" box) are for whoever
    # works on the packaging, not for a first ./scripts/demo: pip shows them unless ignored
    PYTHONWARNINGS=ignore::UserWarning "$VENV/bin/python" -m pip install -q -e "$ROOT$EXTRAS"
    touch "$stamp"
fi
