#!/usr/bin/env bash
# Proof of `cellbench diagnose` on physics it was not written with (make prove; issue 13).
#
# Main table: the independent validation plant (tests/plant, `cellbench_plant`: its own equations, effects in
# other mathematical forms than the catalogue's) generates, per seed, a thesis-layout characterization (HPPC,
# C/20 and high-rate CC discharges) and a ~1 h randomized drive profile with one or two effects hidden. The
# characterization is fitted with the DEFAULT global fit, the drive is diagnosed, and what diagnose names first
# is tabulated against the truth (truth.json, never shown to diagnose). Bench/ageing effects apply to the drive
# only; their characterization is byte-identical to the control's, so its fit is reused.
#
# Second, cheaper table (CATALOGUE=1): the estimator's own generator (`cellbench generate`) with the
# per-pulse-set baseline, i.e. the catalogue checked against itself.
#
# Usage: scripts/prove.sh [BIN_DIR] [SEEDS] [OUT_DIR]     env: JOBS (parallel cases, default 2), CATALOGUE=1,
#        EFFECTS (override the single-effect list), PAIRS=0 (skip the two-effect cases), REUSE=1 (keep the
#        recordings and fits already in OUT_DIR; only diagnose runs again), CONFIRM=1 (the plant also writes a
#        second drive of the same cell and set-up, and each case is diagnosed again with `--confirm` on it: does the
#        check on an independent recording keep the true findings and the controls clean? third table)
set -euo pipefail
BIN=${1:-build/bin}
SEEDS=${2:-"1 2 3 4 5"}
OUT=${3:-build/prove}
JOBS=${JOBS:-2}
if [[ "$SEEDS" =~ ^[0-9]+$ ]]; then SEEDS=$(seq -s ' ' 1 "$SEEDS"); fi
BIN=$(cd "$BIN" && pwd)
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
# Every effect the thesis-layout characterization cannot capture. resistance_temperature and resistance_current
# are physics the global fit identifies from the characterization itself (the 3-4C discharge heats the cell by
# 13-35 K; the pulses and discharges span currents); they are run too, as cases where diagnose must at least not
# name something else.
EFFECTS=${EFFECTS:-"none thermal_second_order ocv_hysteresis extra_rc series_resistance_offset heat_flux_sensor_gain capacity_error ambient_drift resistance_temperature resistance_current"}
PAIRS_LIST=${PAIRS_LIST:-"extra_rc+series_resistance_offset thermal_second_order+capacity_error ocv_hysteresis+heat_flux_sensor_gain series_resistance_offset+ambient_drift"}
[ "${PAIRS:-1}" = 0 ] && PAIRS_LIST=""

run_case() {  # $1 = case (effects joined by +), $2 = seed
  local c=$1 s=$2 d="$OUT/plant/$1-$2" args="" bench_only=1
  mkdir -p "$d"
  for e in ${c//+/ }; do
    args="$args --effect $e"
    case $e in none|series_resistance_offset|heat_flux_sensor_gain|capacity_error|ambient_drift) ;; *) bench_only=0 ;; esac
  done
  # REUSE=1 keeps a case's recordings and fit from an earlier run into the same OUT_DIR (diagnose runs again)
  [ "${CONFIRM:-0}" = 1 ] && args="$args --second-drive"
  if [ "${REUSE:-0}" != 1 ] || [ ! -f "$d/drive.bdf.csv" ] || { [ "${CONFIRM:-0}" = 1 ] && [ ! -f "$d/drive2.bdf.csv" ]; }; then
    rm -f "$d/params.json"
    "$BIN/cellbench_plant" --seed "$s" --layout thesis $args -o "$d" > /dev/null 2>&1
  fi
  local area
  area=$(/usr/bin/python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['area_m2'])" "$d/truth.json")
  local fitdir="$d"
  if [ "$bench_only" = 1 ] && [ "$c" != none ]; then
    # the control's fit serves when the characterization is the same bytes (waits for it)
    while [ ! -f "$OUT/plant/none-$s/params.json" ]; do sleep 2; done
    if cmp -s "$d/hppc.bdf.csv" "$OUT/plant/none-$s/hppc.bdf.csv" && cmp -s "$d/cc_high.bdf.csv" "$OUT/plant/none-$s/cc_high.bdf.csv"; then
      fitdir="$OUT/plant/none-$s"
    fi
  fi
  if [ "$fitdir" = "$d" ] && [ ! -f "$d/params.json" ]; then
    # The heat flux density refers to the cell's surface, which a user knows from its format (the plant's cells
    # are 18650 or 21700 by seed): the fit is told it, as a user would (`fit --area-m2`).
    "$BIN/cellbench" -q fit "$d/hppc.bdf.csv" "$d/cc_low.bdf.csv" "$d/cc_high.bdf.csv" --area-m2 "$area" \
      -o "$d/params.json" > "$d/fit.txt" 2>&1 || echo "fit failed: $d" >&2
  fi
  "$BIN/cellbench" -q diagnose --params "$fitdir/params.json" "$d/drive.bdf.csv" --json "$d/diagnosis.json" \
    --report "$d/report.html" > "$d/diagnose.txt" 2>&1 || echo "diagnose failed: $d" >&2
  /usr/bin/python3 - "$c" "$s" "$d" > "$d/row.tsv" <<'PY'
import json, sys
c, s, d = sys.argv[1:4]
dg = json.load(open(f"{d}/diagnosis.json"))
sig = [f for f in dg["findings"] if f["significant"]]
# Re-identifications of the base fit (kind parameters_wrong: its OCV table, its lumped thermal parameters, its dU/dT
# table) say the characterization's fit is off, not which effect is hidden: counted apart from the effect named
# first (their own column). capacity_error is parameters_wrong too, but it is one of the plant's hidden effects.
PLANT_EFFECTS = {"capacity_error"}
is_refit = lambda f: f.get("kind") == "parameters_wrong" and f["effect"] not in PLANT_EFFECTS
eff = [f for f in sig if not is_refit(f)]
top = eff[0]["effect"] if eff else "none"
b, i = dg["baseline"], dg["improved"]
# the quantity each hidden effect perturbs most (plant README)
aff = {"thermal_second_order": "temperature_rms_c", "ambient_drift": "temperature_rms_c",
       "heat_flux_sensor_gain": "heat_flux_rms_w"}
effs = [e for e in c.split("+") if e != "none"]
q = aff.get(effs[0], "voltage_rms_v") if effs else "voltage_rms_v"
cut = (1 - i[q] / b[q]) if b.get(q) and i.get(q) is not None else 0.0
un = dg.get("unexplained")
print("\t".join([c, s, top, ",".join(f["effect"] for f in eff) or "-",
                 ",".join(f["effect"] for f in sig if is_refit(f)) or "-",
                 q, f"{b[q]:.4g}", f"{i[q]:.4g}", f"{cut:.3f}", "yes" if un else "-",
                 f"{b['voltage_rms_v']*1e3:.2f}", f"{i['voltage_rms_v']*1e3:.2f}"]))
PY
  # CONFIRM=1: the same diagnosis checked on the second drive (the same cell and bench set-up, another profile).
  # Not on the characterization's own recordings: the base parameter set was fitted to them, so any correction
  # tends to look worse there (docs/diagnose.md, session 37).
  if [ "${CONFIRM:-0}" = 1 ]; then
    "$BIN/cellbench" -q diagnose --params "$fitdir/params.json" "$d/drive.bdf.csv" --json "$d/diagnosis-confirm.json" \
      --confirm "$d/drive2.bdf.csv" > "$d/diagnose-confirm.txt" 2>&1 || echo "diagnose --confirm failed: $d" >&2
    /usr/bin/python3 - "$c" "$s" "$d" > "$d/row-confirm.tsv" <<'PY'
import json, sys
c, s, d = sys.argv[1:4]
def top(path):
    dg = json.load(open(path))
    sig = [f for f in dg["findings"] if f["significant"]
           and not (f.get("kind") == "parameters_wrong" and f["effect"] != "capacity_error")]
    return dg, (sig[0]["effect"] if sig else "none"), ",".join(f["effect"] for f in sig) or "-"
_, plain, _ = top(f"{d}/diagnosis.json")
dg, first, named = top(f"{d}/diagnosis-confirm.json")
# the verdicts on the hidden effects' own findings
verdicts = []
for f in dg["findings"]:
    if f["effect"] in c.split("+"):
        verdicts.append(f["effect"] + ":" + ("/".join(x["verdict"] for x in f.get("confirmation", [])) or "not checked"))
print("\t".join([c, s, plain, first, named, ",".join(verdicts) or "-"]))
PY
  fi
  cat "$d/row.tsv"
}
export -f run_case
export BIN OUT

cases=""
for s in $SEEDS; do for e in $EFFECTS $PAIRS_LIST; do cases="$cases $e:$s"; done; done
# controls first: the bench-effect cases wait for their fits
echo $cases | tr ' ' '\n' | grep . | sort -t: -k1,1 -s | awk -F: '$1=="none"{print; next}{rest=rest $0 "\n"} END{printf "%s", rest}' |
  xargs -P "$JOBS" -I{} bash -c 'c={}; run_case "${c%%:*}" "${c##*:}"'

cat "$OUT"/plant/*/row.tsv > "$OUT/plant-rows.tsv"
/usr/bin/python3 - "$OUT/plant-rows.tsv" <<'PY'
import sys, collections
rows = [l.rstrip("\n").split("\t") for l in open(sys.argv[1]) if l.strip()]
single = [r for r in rows if "+" not in r[0]]
pairs = [r for r in rows if "+" in r[0]]
print("\n## Independent plant (thesis layout, default global fit, drive profile diagnosed)\n")
print("| hidden | seed | named first | significant effects | base re-identified (parameters_wrong) | affected quantity | RMS before -> after | cut | unexplained | V RMS mV before -> after |")
print("|---|---|---|---|---|---|---|---|---|---|")
for r in sorted(rows, key=lambda r: (r[0], int(r[1]))):
    print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]} -> {r[7]} | {100*float(r[8]):.0f} % | {r[9]} | {r[10]} -> {r[11]} |")
conf = collections.Counter((r[0], r[2]) for r in single)
truths = sorted({r[0] for r in single})
labels = sorted({r[0] for r in single} | {r[2] for r in single})
print("\nConfusion matrix, one hidden effect (rows: hidden, columns: named first)\n")
print("| hidden \\ named | " + " | ".join(labels) + " |")
print("|---" * (len(labels) + 1) + "|")
for a in truths:
    print(f"| {a} | " + " | ".join(str(conf[(a, b)] or "") for b in labels) + " |")
# Issue 13's acceptance counts the effects an HPPC cannot capture; resistance_temperature and resistance_current are
# identified by the default global fit from the characterization itself (the parameter set holds them, diagnose
# skips them), so there the right answer is "none" or the effect itself, and naming another effect is the error.
# extra_rc joined them in session 19: the plant's slow pairs act on the HPPC as on the drive, and the global fit's
# slow pair (params extensions.extra_rc) takes them from the HPPC's 1 h rests (drive RMS then at control level).
CAPTURED = {"resistance_temperature", "resistance_current", "extra_rc"}
eff = [r for r in single if r[0] != "none" and r[0] not in CAPTURED]
cap = [r for r in single if r[0] in CAPTURED]
ok = sum(r[0] == r[2] for r in eff)
ctrl = [r for r in single if r[0] == "none"]
fp = sum(r[3] != "-" for r in ctrl)
cuts = [float(r[8]) for r in eff if r[0] == r[2]]
refit_ctrl = sum(r[4] != "-" for r in ctrl)
print(f"\nright effect first (effects an HPPC cannot capture): {ok} of {len(eff)} ({100*ok/max(len(eff),1):.0f} %)")
if cap:
    wrong = sum(r[2] not in ("none", r[0]) for r in cap)
    print(f"effects the characterization captures ({', '.join(sorted(CAPTURED))}): another effect named in {wrong} of {len(cap)}")
print(f"controls with a significant effect finding: {fp} of {len(ctrl)} "
      f"(with a base re-identification, parameters_wrong: {refit_ctrl} of {len(ctrl)})")
if cuts:
    print(f"RMS cut of the affected quantity when named right: median {100*sorted(cuts)[len(cuts)//2]:.0f} %, "
          f">= 50 % in {sum(c >= 0.5 for c in cuts)} of {len(cuts)}")
if pairs:
    # A pair counts when every member the characterization cannot capture is named (a captured member, e.g.
    # extra_rc, is in the parameter set: diagnose rightly has nothing to add for it).
    def named_all(r):
        named = [x.split(':')[0] for x in r[3].split(',')]
        return all(e in named for e in r[0].split('+') if e not in CAPTURED)
    both = sum(named_all(r) for r in pairs)
    part = sum(any(e in CAPTURED for e in r[0].split('+')) for r in pairs)
    print(f"two-effect cases with both named: {both} of {len(pairs)} ({100*both/len(pairs):.0f} %)"
          + (f"; in {part} of them one member is captured by the fit and only the other must be named" if part else ""))
PY

if [ "${CONFIRM:-0}" = 1 ]; then
  cat "$OUT"/plant/*/row-confirm.tsv > "$OUT/plant-confirm-rows.tsv" 2>/dev/null || true
  /usr/bin/python3 - "$OUT/plant-confirm-rows.tsv" <<'PY'
import sys
rows = [l.rstrip("\n").split("\t") for l in open(sys.argv[1]) if l.strip()]
print("\n## diagnose --confirm on a second drive of the same cell and set-up\n")
print("| hidden | seed | named first without | named first with --confirm | significant with | verdicts on the hidden effects' findings |")
print("|---|---|---|---|---|---|")
for r in sorted(rows, key=lambda r: (r[0], int(r[1]))):
    print("| " + " | ".join(r) + " |")
CAPTURED = {"resistance_temperature", "resistance_current", "extra_rc"}
single = [r for r in rows if "+" not in r[0] and r[0] != "none" and r[0] not in CAPTURED]
ctrl = [r for r in rows if r[0] == "none"]
pairs = [r for r in rows if "+" in r[0]]
def named_all(r, col):
    named = [x for x in r[col].split(",")]
    return all(e in named for e in r[0].split("+") if e not in CAPTURED)
contradicted = sum("contradicts" in v for r in single + pairs for v in r[5].split(",") if v.split(":")[0] in r[0].split("+"))
print(f"\nright effect first without -> with --confirm: {sum(r[0] == r[2] for r in single)} -> "
      f"{sum(r[0] == r[3] for r in single)} of {len(single)}; controls with a significant effect: "
      f"{sum(r[2] != 'none' for r in ctrl)} -> {sum(r[4] != '-' for r in ctrl)} of {len(ctrl)}; "
      f"pairs both named with --confirm: {sum(named_all(r, 4) for r in pairs)} of {len(pairs)}; "
      f"hidden effects' findings the second drive contradicts: {contradicted}")
PY
fi

if [ "${CATALOGUE:-0}" = 1 ]; then
  rows="$OUT/catalogue-rows.tsv"; : > "$rows"
  for e in none entropic_heat thermal_second_order resistance_temperature resistance_current ocv_hysteresis extra_rc capacity_error series_resistance_offset heat_flux_sensor_gain ambient_drift; do
    for s in $SEEDS; do
      d="$OUT/catalogue/$e-$s"
      "$BIN/cellbench" -q generate --effect "$e" --seed "$s" -o "$d" > /dev/null
      "$BIN/cellbench" -q fit --per-pulse-set "$d/characterization.bdf.csv" -o "$d/params.json" > /dev/null 2>&1
      "$BIN/cellbench" -q diagnose --params "$d/params.json" "$d/validation.bdf.csv" --json "$d/diagnosis.json" > /dev/null 2>&1
      /usr/bin/python3 -c "
import json,sys; dg=json.load(open(sys.argv[3])); sig=[f['effect'] for f in dg['findings'] if f['significant']]
print(sys.argv[1], sys.argv[2], sig[0] if sig else 'none', ','.join(sig) or '-', sep='\t')" "$e" "$s" "$d/diagnosis.json" >> "$rows"
    done
  done
  /usr/bin/python3 - "$rows" <<'PY'
import sys
rows = [l.rstrip("\n").split("\t") for l in open(sys.argv[1]) if l.strip()]
print("\n## Catalogue against itself (cellbench generate, per-pulse-set baseline)\n")
print("| hidden | seed | named first | all significant |\n|---|---|---|---|")
for r in rows: print("| " + " | ".join(r) + " |")
print(f"\n{sum(r[0] == r[2] for r in rows)} of {len(rows)} named correctly")
PY
fi
