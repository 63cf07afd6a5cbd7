#!/usr/bin/env bash
# How much of an mlsss command's time is the VM's free page reporting: runs the same binary on
# the same command with the guest's page reporting as found ("reporting") and with it deferred
# ("deferred": a freed page is reported to the hypervisor only after 60 s free, so memory freed
# by the previous run or earlier in this one is faulted in again without a trip to the host), in
# balanced order (reporting, deferred, deferred, reporting; repeated), a pause before every run,
# and prints each run and the medians (GNU time's wall, CPU user and system, peak; huge-page
# faults from /proc/vmstat). The setting found is put back on exit.
#
#   sudo scripts/page_reporting_race.sh BIN CYCLES -- MLSSS_ARGS...
#
# e.g. the full-size process of scripts/speed_bench.sh, 3 cycles (12 runs):
#
#   scripts/page_reporting_race.sh target/release/mlsss 3 -- process CAPTURE \
#       --calib truth --until fit --holdout 3 --components 4 --block 6
#
# Each run gets a fresh `--out` folder under $RACE_OUT (default target/page-reporting-race),
# deleted after the run. GAP=S sets the pause (default 8 s; mainline kernels report free pages
# within ~2 s, so a "reporting" run starts from memory the host has taken back).
#
# A diagnosis of the benchmark machine, not a setting of mlsss: it needs root and a guest kernel
# with the `page_reporting` module's `min_free_ms` parameter (the build VM's Firecracker kernel).
set -euo pipefail
usage="usage: scripts/page_reporting_race.sh BIN CYCLES -- MLSSS_ARGS..."
[ $# -ge 4 ] && [ "$3" = "--" ] || { echo "$usage" >&2; exit 2; }
BIN=$1
CYCLES=$2
shift 3
[ -x "$BIN" ] || { echo "error: $BIN is not an executable" >&2; exit 2; }
case $CYCLES in '' | *[!0-9]* | 0) echo "error: CYCLES must be a positive integer" >&2; exit 2 ;; esac
command -v /usr/bin/time >/dev/null || { echo "error: GNU time (/usr/bin/time) is missing: apt-get install time" >&2; exit 1; }
PARAM=/sys/module/page_reporting/parameters/min_free_ms
[ -w "$PARAM" ] || { echo "error: $PARAM is missing or not writable (needs root and a kernel with it)" >&2; exit 1; }
FOUND=$(cat "$PARAM")
trap 'echo "$FOUND" > "$PARAM"' EXIT
OUT=${RACE_OUT:-target/page-reporting-race}
GAP=${GAP:-8}
mkdir -p "$OUT"
RESULTS="$OUT/results.tsv"
: > "$RESULTS"

thp_faults() { awk '$1 == "thp_fault_alloc" { print $2 }' /proc/vmstat; }

# run LABEL MIN_FREE_MS N: run number N with the reporting delay MIN_FREE_MS, appended to the
# results.
run() {
    local label=$1 delay=$2 n=$3
    local dir="$OUT/$label-$n"
    rm -rf "$dir"
    echo "$delay" > "$PARAM"
    sleep "$GAP"
    local before
    before=$(thp_faults)
    /usr/bin/time -f "%e %U %S %M" -o "$OUT/time" "$BIN" "${ARGS[@]}" --out "$dir" \
        > /dev/null 2> "$OUT/$label-$n.err" || { echo "error: $BIN failed, see $OUT/$label-$n.err" >&2; exit 1; }
    local huge=$(($(thp_faults) - before))
    read -r wall user sys peak < "$OUT/time"
    rm -rf "$dir"
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$label" "$wall" "$user" "$sys" "$peak" "$huge" >> "$RESULTS"
    printf '%-9s run %d: wall %6.2f s  user %6.2f s  sys %5.2f s  peak %5.2f GiB  huge-page faults %d\n' \
        "$label" "$n" "$wall" "$user" "$sys" "$(echo "$peak / 1048576" | bc -l)" "$huge"
}

ARGS=("$@")
echo "page reporting found at min_free_ms=$FOUND; deferred runs use 60000"
for cycle in $(seq "$CYCLES"); do
    run reporting "$FOUND" $((2 * cycle - 1))
    run deferred 60000 $((2 * cycle - 1))
    run deferred 60000 $((2 * cycle))
    run reporting "$FOUND" $((2 * cycle))
done

# median LABEL COLUMN: the median of one column over the label's runs.
median() {
    awk -v l="$1" -v c="$2" '$1 == l { print $c }' "$RESULTS" | sort -g \
        | awk '{ v[NR] = $1 } END { print (NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2) }'
}
for label in reporting deferred; do
    printf '%-9s median: wall %6.2f s  user %6.2f s  sys %5.2f s  huge-page faults %s\n' \
        "$label" "$(median "$label" 2)" "$(median "$label" 3)" "$(median "$label" 4)" "$(median "$label" 6)"
done
