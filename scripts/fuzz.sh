#!/usr/bin/env bash
# Builds every cargo-fuzz target of fuzz/ and runs each for SECONDS, then prints one line per
# target: executions, coverage (libFuzzer's edge count `cov` and feature count `ft`), corpus
# size, and crashes. Exits non-zero when any target crashed.
#
#   scripts/fuzz.sh SECONDS [TARGET...]     (default: every target)
#
# Targets are built optimised with debug assertions and overflow checks on (cargo-fuzz's
# default). FUZZ_SANITIZER: address (the default) or none, which builds and runs faster and
# still finds panics, overflows and aborts, only not memory errors (which only the unsafe
# code of src/simd and the dependencies could have).
# No nightly toolchain is needed: RUSTC_BOOTSTRAP=1 lets the stable one take -Z flags.
# Seeds come from fuzz/seeds/TARGET (committed); what a run learns goes to fuzz/corpus/TARGET,
# crashes to fuzz/artifacts/TARGET, a failed run's whole log to fuzz/logs (none is committed).
set -euo pipefail
cd "$(dirname "$0")/../fuzz"

if [ $# -lt 1 ] || ! [[ $1 =~ ^[0-9]+$ ]]; then
  echo "usage: scripts/fuzz.sh SECONDS [TARGET...]" >&2
  exit 2
fi
seconds=$1
shift
export RUSTC_BOOTSTRAP=1
sanitizer=${FUZZ_SANITIZER:-address}
command -v cargo-fuzz >/dev/null 2>&1 || cargo install cargo-fuzz --locked
if [ $# -gt 0 ]; then targets=("$@"); else mapfile -t targets < <(cargo fuzz list); fi

start=$(date +%s)
if [ $# -gt 0 ]; then
  for t in "${targets[@]}"; do cargo fuzz build -s "$sanitizer" "$t"; done
else
  cargo fuzz build -s "$sanitizer"
fi
echo "fuzz: built ${#targets[@]} targets in $(( $(date +%s) - start )) s (sanitizer: $sanitizer)"

failed=0
printf '%-10s %10s %8s %8s %7s %8s %8s\n' target execs exec/s cov ft corpus crashes
for t in "${targets[@]}"; do
  mkdir -p "corpus/$t" "artifacts/$t"
  log=$(mktemp)
  # `http` keeps one service (its tokio runtime, pools and store) in a static for the whole
  # run. libFuzzer sees that memory stay and stops checking leaks after each input, but
  # LeakSanitizer still checks at exit, finds what the service's threads hold at that
  # moment (a blocking-pool thread that a streamed download was starting, BENCHMARKS
  # §16.6) and libFuzzer blames the last input, whatever it was. libFuzzer's
  # -detect_leaks=0 turns off only its own per-input check; the check at exit is
  # LeakSanitizer's, turned off by ASAN_OPTIONS (§16.7: with the flag alone, 45 minutes
  # ended in the same report). The parsers keep nothing between inputs, so their leaks
  # are still checked, at each input and at exit.
  extra=()
  asan_options=${ASAN_OPTIONS:-}
  if [ "$t" = http ]; then
    extra+=(-detect_leaks=0)
    asan_options="${asan_options:+$asan_options:}detect_leaks=0"
  fi
  set +e
  ASAN_OPTIONS="$asan_options" cargo fuzz run -s "$sanitizer" "$t" "corpus/$t" "seeds/$t" -- \
    -max_total_time="$seconds" -timeout=10 -rss_limit_mb=4096 -print_final_stats=1 \
    -artifact_prefix="artifacts/$t/" "${extra[@]}" >"$log" 2>&1
  rc=$?
  set -e
  # The last status line: "#N DONE cov: C ft: F corp: K/S exec/s: E rss: R".
  line=$(grep -E '^#[0-9]+' "$log" | tail -n 1)
  execs=$(sed -nE 's/^stat::number_of_executed_units: *([0-9]+).*/\1/p' "$log" | tail -n 1)
  persec=$(sed -nE 's/^stat::average_exec_per_sec: *([0-9]+).*/\1/p' "$log" | tail -n 1)
  cov=$(sed -nE 's/.* cov: ([0-9]+).*/\1/p' <<<"$line")
  ft=$(sed -nE 's/.* ft: ([0-9]+).*/\1/p' <<<"$line")
  corp=$(sed -nE 's/.* corp: ([0-9]+).*/\1/p' <<<"$line")
  crashes=$(find "artifacts/$t" -type f | wc -l)
  printf '%-10s %10s %8s %8s %7s %8s %8s\n' "$t" "${execs:-?}" "${persec:-?}" "${cov:-?}" \
    "${ft:-?}" "${corp:-?}" "$crashes"
  if [ "$rc" -ne 0 ] || [ "$crashes" -ne 0 ]; then
    failed=1
    mkdir -p logs
    cp "$log" "logs/$t-$start.txt"
    echo "fuzz: $t exited $rc; its log (whole in fuzz/logs/$t-$start.txt):" >&2
    tail -n 40 "$log" >&2
  fi
  rm -f "$log"
done
echo "fuzz: total $(( $(date +%s) - start )) s"
exit "$failed"
