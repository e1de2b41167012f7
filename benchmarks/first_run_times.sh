#!/usr/bin/env bash
# What a new user waits for: the README's main command (its `<!-- command: main -->` block, less
# the apt line, which needs root and is not ours to time) from a fresh clone of this repository's
# committed HEAD, with nothing cached. HOME is an empty temporary folder, so pip's cache,
# kintinuous' scenario cache (~/.cache/kintinuous) and numba's cache (NUMBA_CACHE_DIR, set inside
# it) all start empty. It times the install (venv, activation, pip install) and each kintinuous
# command twice: its first run (which renders scenes and compiles kernels) and a second run of
# the same command (which loads both), and prints them with the machine and its load average at
# the start and the end: on a shared machine the load decides as much as the code does.
#
#     benchmarks/first_run_times.sh            # from anywhere inside a checkout
#
# Each step runs in a session of its own, so that a signal ends it with every process it started
# (pip's builds, the compile workers of a warm-up), and the temporary folder goes on any exit.
set -euo pipefail

checkout=$(git -C "$(dirname "$0")" rev-parse --show-toplevel)
work=$(mktemp -d "${TMPDIR:-/tmp}/kintinuous-first-run.XXXXXX")
step_pid=""

end_step() {
    if [[ -n $step_pid ]]; then
        kill -TERM -- "-$step_pid" 2>/dev/null || true
        wait "$step_pid" 2>/dev/null || true
        step_pid=""
    fi
}
trap 'end_step; rm -rf "$work"' EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

load() { cut -d' ' -f1-3 /proc/loadavg; }
now() { date +%s.%N; }
seconds_since() { awk -v start="$1" -v end="$(now)" 'BEGIN { printf "%.1f", end - start }'; }

# Runs one step of the command in its own session and prints its wall time, then what the step
# said about compiling (the notice and its time); its output's tail is shown when it fails.
timed() {
    local label=$1 step=$2 start
    start=$(now)
    setsid bash -c "$step" >"$work/step.log" 2>&1 &
    step_pid=$!
    if ! wait "$step_pid"; then
        step_pid=""
        echo "failed: $step" >&2
        tail -n 20 "$work/step.log" >&2
        exit 1
    fi
    step_pid=""
    printf '%-14s %8s s  %s\n' "$label" "$(seconds_since "$start")" "$step"
    tr '\r' '\n' <"$work/step.log" | grep -a 'compil' | sed 's/^/                 /' || true
}

main_command() {
    awk '/<!-- command: main -->/ { found = 1; next }
         found && /^```bash/ { inside = 1; next }
         inside && /^```/ { exit }
         inside && !/apt-get/ { print }' "$checkout/README.md"
}

# pyenv's shims look for their interpreters under $HOME unless told where they are.
if [[ -z ${PYENV_ROOT:-} ]] && command -v pyenv >/dev/null; then
    PYENV_ROOT=$(pyenv root)
    export PYENV_ROOT
fi
export HOME="$work/home" NUMBA_CACHE_DIR="$work/home/.cache/numba"
unset KINTINUOUS_CACHE XDG_CACHE_HOME PIP_CACHE_DIR
mkdir -p "$HOME"

commit=$(git -C "$checkout" rev-parse --short HEAD)
echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ *//'), $(nproc) cores"
echo "commit: $commit (HEAD of $checkout, cloned into a temporary folder)"
echo "load average at the start: $(load)"
total_start=$(now)

timed clone "git clone --quiet '$checkout' '$work/clone'"
cd "$work/clone"
IFS=$'\n' read -r -d '' -a steps < <(main_command | sed 's/ && /\n/g' && printf '\0')
commands=()
for step in "${steps[@]}"; do
    case $step in
        ". "*/activate)
            # activation changes this shell's PATH, for the steps after it
            # shellcheck disable=SC1090
            source "${step#. }"
            printf '%-14s %8s s  %s\n' install 0.0 "$step"
            ;;
        kintinuous\ *)
            commands+=("$step")
            timed "first run" "$step"
            ;;
        *) timed install "$step" ;;
    esac
done
first_done=$(now)
for step in "${commands[@]}"; do
    timed "second run" "$step"
done
first_run=$(awk -v a="$total_start" -v b="$first_done" 'BEGIN { printf "%.1f", b - a }')
echo "from the clone to the first runs' last output: $first_run s"
echo "load average at the end: $(load)"
