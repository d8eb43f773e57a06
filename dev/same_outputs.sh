#!/usr/bin/env bash
# Shows that a refactor changed no output: runs the same fixed-seed work
# with two nerflabel binaries and compares the sha256 of every file written
# (two fits with different settings, labels with --depth, a synth Parquet
# file, and a generated fixture). Both fit and label the same scan, made by
# the first binary. Prints nothing but the verdict when all files match.
#
#   git worktree add /tmp/before <commit> && (cd /tmp/before && cargo build --release)
#   dev/same_outputs.sh /tmp/before/target/release/nerflabel target/release/nerflabel
set -euo pipefail
[ $# -eq 2 ] || { echo "usage: $0 BEFORE_BINARY AFTER_BINARY" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$(readlink -f "$1")" fixture "$work/scan" --scene tabletop --frames 24 --width 160 --height 120 --seed 5 --realistic >/dev/null
outputs() {
  local bin out
  bin=$(readlink -f "$1"); out=$2
  mkdir -p "$out" && cp -r "$work/scan" "$out/scan" && cd "$out"
  # Relative paths: the model header records the scan path as given.
  "$bin" fixture fixture --scene tabletop --frames 24 --width 160 --height 120 --seed 5 --realistic >/dev/null 2>&1
  "$bin" fit scan --steps 150 --seed 7 --model m.nlf >/dev/null 2>&1
  "$bin" fit scan --steps 30 --seed 7 --preset fast --holdout 0 --lambda-depth 0.2 --learning-rate 0.005 \
    --no-pose-refine --model m2.nlf >/dev/null 2>&1
  "$bin" label scan --model m.nlf --boxes scan/gt/boxes_loose.json --out labels --depth >/dev/null 2>&1
  "$bin" synth scan --model m.nlf --boxes scan/gt/boxes_user.json --n 6 --out s.parquet >/dev/null 2>&1
  # JSON files hold versions and timings; everything else must match.
  find . -type f \( -name '*.nlf' -o -path './labels/*' -o -name '*.parquet' -o -path './fixture/*' \) ! -name '*.json' \
    | sort | xargs sha256sum
}
(outputs "$1" "$work/before") > "$work/before.sha"
(outputs "$2" "$work/after") > "$work/after.sha"
if diff "$work/before.sha" "$work/after.sha"; then
  echo "same outputs: $(wc -l < "$work/before.sha") files byte-identical"
else
  echo "outputs differ (lines above: < before, > after)"
  exit 1
fi
