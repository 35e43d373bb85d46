#!/usr/bin/env bash
# Regenerates the proof table of `cellbench diagnose` (make prove): for every effect id of the catalogue and a
# control cell, and for each seed, generate a characterization and a validation recording with that effect
# hidden, fit the characterization, diagnose the validation, and tabulate what diagnose names first, against
# the truth (never shown to diagnose). Usage: scripts/prove.sh [BIN_DIR] [SEEDS] [OUT_DIR]
set -euo pipefail
BIN=${1:-build/bin}
SEEDS=${2:-"1 2 3"}
OUT=${3:-build/prove}
EFFECTS="none entropic_heat thermal_second_order resistance_temperature resistance_current ocv_hysteresis extra_rc capacity_error series_resistance_offset heat_flux_sensor_gain ambient_drift"
mkdir -p "$OUT"
rows="$OUT/rows.tsv"
: > "$rows"
for e in $EFFECTS; do
  for s in $SEEDS; do
    d="$OUT/$e-$s"
    "$BIN/cellbench" -q generate --effect "$e" --seed "$s" -o "$d" > /dev/null
    # the per-pulse-set baseline the catalogue proof was designed with (tests/data/diagnose_proof_test.cpp says why)
    "$BIN/cellbench" -q fit --per-pulse-set "$d/characterization.bdf.csv" -o "$d/params.json" --json "$d/fit-summary.json" > /dev/null
    "$BIN/cellbench" -q simulate --params "$d/params.json" "$d/characterization.bdf.csv" --json "$d/char-metrics.json" > /dev/null
    "$BIN/cellbench" -q diagnose --params "$d/params.json" "$d/validation.bdf.csv" --json "$d/diagnosis.json" \
      --report "$d/report.html" > /dev/null
    /usr/bin/python3 - "$e" "$s" "$d" >> "$rows" <<'PY'
import json, sys
e, s, d = sys.argv[1:4]
dg = json.load(open(f"{d}/diagnosis.json")); cm = json.load(open(f"{d}/char-metrics.json"))
sig = [f["effect"] for f in dg["findings"] if f["significant"]]
top = sig[0] if sig else "none"
b, i = dg["baseline"], dg["improved"]
fmt = lambda x, k: "-" if x is None else f"{x*k:.2f}"
print("\t".join([e, s, top, ",".join(sig) or "-", fmt(cm["voltage"]["rms_v"], 1e3),
                 fmt(b["voltage_rms_v"], 1e3), fmt(i["voltage_rms_v"], 1e3), fmt(b["temperature_rms_c"], 1),
                 fmt(i["temperature_rms_c"], 1), fmt(b["heat_flux_rms_w"], 1), fmt(i["heat_flux_rms_w"], 1)]))
PY
    tail -n 1 "$rows"
  done
done
/usr/bin/python3 - "$rows" <<'PY'
import sys, collections
rows = [l.rstrip("\n").split("\t") for l in open(sys.argv[1]) if l.strip()]
print("\n| hidden | seed | named first | all significant | HPPC fit V RMS mV | V RMS mV before -> after | T RMS degC before -> after | heat flux RMS W before -> after |")
print("|---|---|---|---|---|---|---|---|")
for r in rows:
    print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} -> {r[6]} | {r[7]} -> {r[8]} | {r[9]} -> {r[10]} |")
conf = collections.Counter((r[0], r[2]) for r in rows)
labels = sorted({r[0] for r in rows} | {r[2] for r in rows})
print("\nConfusion matrix (rows: hidden, columns: named first)\n")
print("| hidden \\ named | " + " | ".join(labels) + " |")
print("|---" * (len(labels) + 1) + "|")
for a in sorted({r[0] for r in rows}):
    print(f"| {a} | " + " | ".join(str(conf[(a, b)] or "") for b in labels) + " |")
ok = sum(r[0] == r[2] for r in rows)
print(f"\n{ok} of {len(rows)} cases named correctly")
PY
