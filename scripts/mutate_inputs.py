#!/usr/bin/env python3
"""Mutation campaign for the recording readers of the `cellbench` CLI (issue 16). Python 3 standard library only.

From the real recordings in ../shared/data/p45b it makes N mutated files of each recording kind (BDF CSV,
Neware export, DewesoftX export), runs the CLI on each with a timeout and classifies the outcome:

  crash         killed by a signal, or an exit status other than 0 and 1
  hang          still running after --timeout seconds
  clear error   exit 1 with one "error: " line naming the mutated file
  unclear error exit 1 without such a line
  success ok    exit 0 and the result is right: equal (within tolerance) to the unmutated baseline, or the
                mutation is one the reader may legitimately accept (a plausible value, a dropped row, ...) and the
                result is finite and sane, or what was wrong was reported in a warning
  SILENT WRONG  exit 0 with a result that differs from the baseline, or with non-finite numbers, for a
                mutation that corrupts the data and was not reported

Kinds and commands:
  bdf      cellbench simulate --params config/cells/p45b-thesis.json MUTANT --json m.json   (cc_4c_30degC.bdf.csv)
           checked: voltage RMS error against the baseline
  neware   cellbench import --neware MUTANT -o out.bdf.csv                                    (rw_30degC_neware.csv)
           checked: rows, duration and charge throughput of the output against the baseline
  dewesoft cellbench import --neware rw_30degC_neware.csv --dewesoft MUTANT -o out.bdf.csv    (rw_30degC_dewesoft.csv)
           checked: the clock offset applied, and the mean surface temperature of the output

Usage: scripts/mutate_inputs.py [--bin build/bin] [--count 300] [--timeout 10] [--jobs 1] [--kinds bdf,neware,dewesoft]
Exit status 1 when any crash, hang or silent wrong success was seen.
"""
import argparse
import concurrent.futures
import csv
import io
import json
import math
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# Mutations the reader must refuse or report (they make the data wrong) and ones it may accept as they are
# (the data stays a plausible recording; the result may change, but only as the data did).
CORRUPTING = {"huge_value", "overflow_value", "nonfinite_value", "garbage_cell", "missing_cell", "cut_mid_line",
              "time_jump", "time_back", "binary_bytes", "garbage_char", "header_mangle", "long_line", "empty",
              "header_only", "impossible_value", "nul_block"}
PLAUSIBLE = {"digit_flip", "delete_row", "duplicate_row", "truncate_rows", "crlf", "bom", "swap_columns",
             "small_scale", "blank_lines", "whitespace"}


def split_lines(text):
    return text.split("\n")


def data_rows(lines):
    # indices of non-empty data lines (after the header)
    return [i for i in range(1, len(lines)) if lines[i].strip()]


def mutate(text, rng, kind, name):
    """Returns the mutated text (str or bytes)."""
    lines = split_lines(text)
    rows = data_rows(lines)
    ncol = len(lines[0].split(","))
    # Columns with numbers (skip text columns such as Neware's "Step Type").
    sample = lines[rows[len(rows) // 2]].split(",")
    numeric = [c for c in range(min(ncol, len(sample))) if re.fullmatch(r"[-+0-9.eE]+", sample[c].strip() or "x")]

    def set_cell(value, col=None, row=None):
        r = row if row is not None else rng.choice(rows)
        cells = lines[r].split(",")
        c = col if col is not None else rng.choice(numeric)
        if c < len(cells):
            cells[c] = value
        lines[r] = ",".join(cells)
        return "\n".join(lines)

    time_col = 0
    header = [h.strip().lower() for h in lines[0].split(",")]
    for c, h in enumerate(header):
        if h.startswith("test time") or h == "time" or h == "time(s)":
            time_col = c
            break

    if name == "huge_value":
        return set_cell(rng.choice(["1e308", "-1e308", "1.7e308", "9e300"]))
    if name == "overflow_value":
        return set_cell(rng.choice(["1e999", "-1e999", "1e400"]))
    if name == "nonfinite_value":
        return set_cell(rng.choice(["inf", "-inf", "Infinity", "nan", "NaN"]), col=rng.choice([c for c in numeric if c != time_col] or numeric))
    if name == "impossible_value":
        return set_cell(rng.choice(["1e6", "-4e5", "123456", "-99999"]), col=rng.choice([c for c in numeric if c != time_col] or numeric))
    if name == "garbage_cell":
        return set_cell(rng.choice(["abc", "1.2.3", "--5", "0x1p3", "1e", "", "12,5"]), col=rng.choice(numeric))
    if name == "missing_cell":
        r = rng.choice(rows)
        cells = lines[r].split(",")
        del cells[rng.randrange(len(cells))]
        lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "cut_mid_line":
        r = rng.choice(rows[len(rows) // 4:])
        cut = sum(len(l) + 1 for l in lines[:r]) + rng.randrange(1, max(2, len(lines[r])))
        return text[:cut]
    if name == "time_jump":
        start = rng.choice(rows[len(rows) // 10: -2])
        jump = rng.choice([600.0, 3600.0, 86400.0, 1e6])
        for r in rows:
            if r >= start:
                cells = lines[r].split(",")
                try:
                    cells[time_col] = repr(float(cells[time_col]) + jump)
                except ValueError:
                    pass
                lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "time_back":
        r = rng.choice(rows[len(rows) // 10:])
        cells = lines[r].split(",")
        try:
            cells[time_col] = repr(float(cells[time_col]) - rng.choice([5.0, 100.0, 1e4]))
        except ValueError:
            pass
        lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "binary_bytes":
        data = bytearray(text.encode())
        pos = rng.randrange(len(data))
        data[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
        if 0 not in data[pos:pos + 64]:
            data[pos] = 0
        return bytes(data)
    if name == "nul_block":
        data = bytearray(text.encode())
        pos = rng.randrange(len(data))
        data[pos:pos + 4096] = bytes(4096)
        return bytes(data)
    if name == "garbage_char":
        r = rng.choice(rows)
        cells = lines[r].split(",")
        c = rng.choice(numeric)
        cell = cells[c]
        if cell:
            k = rng.randrange(len(cell))
            cells[c] = cell[:k] + rng.choice("xZ#;:/ '\"") + cell[k + 1:]
        lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "header_mangle":
        cells = lines[0].split(",")
        c = rng.choice([time_col] + numeric[:3])
        cells[c] = cells[c][::-1]
        lines[0] = ",".join(cells)
        return "\n".join(lines)
    if name == "long_line":
        r = rng.choice(rows)
        lines[r] = lines[r] + "," + "9" * rng.choice([70000, 500000])
        return "\n".join(lines)
    if name == "empty":
        return ""
    if name == "header_only":
        return lines[0] + "\n"
    # plausible ones
    if name == "digit_flip":
        # a digit after the first two significant ones: a small change in value
        r = rng.choice(rows)
        cells = lines[r].split(",")
        c = rng.choice([c for c in numeric if c != time_col] or numeric)
        cell = cells[c]
        digits = [k for k, ch in enumerate(cell) if ch.isdigit()]
        if len(digits) > 3 and "e" not in cell.lower():
            k = rng.choice(digits[3:])
            cells[c] = cell[:k] + str(rng.randrange(10)) + cell[k + 1:]
        lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "delete_row":
        for _ in range(rng.randrange(1, 20)):
            r = rng.randrange(1, len(lines) - 1)
            del lines[r]
        return "\n".join(lines)
    if name == "duplicate_row":
        r = rng.choice(rows)
        lines.insert(r, lines[r])
        return "\n".join(lines)
    if name == "truncate_rows":
        keep = rng.randrange(len(rows) // 2, len(rows))
        return "\n".join(lines[:keep + 1]) + "\n"
    if name == "crlf":
        return text.replace("\n", "\r\n")
    if name == "bom":
        return "\ufeff" + text
    if name == "swap_columns" and kind == "bdf":
        a, b = rng.sample(range(ncol), 2)
        out = []
        for l in lines:
            cells = l.split(",")
            if len(cells) == ncol:
                cells[a], cells[b] = cells[b], cells[a]
            out.append(",".join(cells))
        return "\n".join(out)
    if name == "small_scale":
        r = rng.choice(rows)
        cells = lines[r].split(",")
        c = rng.choice([c for c in numeric if c != time_col] or numeric)
        try:
            cells[c] = repr(float(cells[c]) * (1 + rng.uniform(-0.01, 0.01)))
        except ValueError:
            pass
        lines[r] = ",".join(cells)
        return "\n".join(lines)
    if name == "blank_lines":
        r = rng.choice(rows)
        lines.insert(r, "")
        return "\n".join(lines)
    if name == "whitespace":
        r = rng.choice(rows)
        lines[r] = " " + lines[r].replace(",", " ,\t")
        return "\n".join(lines)
    return text


def run(cmd, timeout):
    t0 = time.monotonic()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, errors="replace")
    except subprocess.TimeoutExpired:
        return None, "", "", time.monotonic() - t0
    return p.returncode, p.stdout, p.stderr, time.monotonic() - t0


def read_bdf(path):
    with open(path, newline="") as f:
        r = csv.reader(f)
        header = [h.strip() for h in next(r)]
        cols = {h: i for i, h in enumerate(header)}
        rows = [row for row in r if row]
    def col(name):
        i = cols.get(name)
        if i is None:
            return []
        return [float(row[i]) if row[i].strip() else math.nan for row in rows]
    return header, col


def summarize(kind, out_path, stdout):
    """Numbers that characterise a successful result."""
    if kind == "bdf":
        with open(out_path) as f:
            m = json.load(f)
        v = m.get("voltage")
        return {"rms_v": v["rms_v"] if v else None, "samples": m.get("samples")}
    header, col = read_bdf(out_path)
    t = col("Test Time / s")
    i = col("Current / A")
    v = col("Voltage / V")
    ah = sum(abs(i[k]) * (t[k + 1] - t[k]) for k in range(len(t) - 1)) / 3600.0
    s = {"rows": len(t), "duration_s": t[-1] - t[0], "throughput_ah": ah,
         "vmax": max(v), "vmin": min(v), "finite": all(math.isfinite(x) for x in t + v + i)}
    if kind == "dewesoft":
        m = re.search(r"clock offset applied to .*?: ([-+0-9.]+) s", stdout)
        s["offset_s"] = float(m.group(1)) if m else None
        ts = [x for x in col("Surface Temperature / degC") if math.isfinite(x)]
        s["mean_surface_c"] = sum(ts) / len(ts) if ts else None
        s["surface_ok"] = all(-100 <= x <= 300 for x in ts)
    return s


REPORTED = re.compile(r"GAP|impossible|ends mid-line|read as empty|cut short|dropped")  # a "repaired N timestamps" warning does not report a gap


def judge(kind, mutation, base, got, stderr):
    """'ok' or a reason why the success is silently wrong."""
    if kind == "bdf":
        rms = got["rms_v"]
        if rms is None or not math.isfinite(rms):
            return "no finite voltage RMS"
        close = abs(rms - base["rms_v"]) <= 0.05 * base["rms_v"] + 1e-5
    else:
        if not got["finite"]:
            return "non-finite values in the output"
        if not (0 <= got["vmin"] and got["vmax"] <= 10):
            return "voltage outside 0..10 V in the output"
        close = (abs(got["duration_s"] - base["duration_s"]) <= 0.01 * base["duration_s"] + 1 and
                 abs(got["throughput_ah"] - base["throughput_ah"]) <= 0.01 * base["throughput_ah"] + 1e-3)
        if kind == "dewesoft":
            if got["offset_s"] is None:
                return "no clock offset printed"
            if abs(got["offset_s"] - base["offset_s"]) > 2.0:
                return "clock offset %+.1f s instead of %+.1f s" % (got["offset_s"], base["offset_s"])
            if not got["surface_ok"]:
                return "surface temperature outside -100..300 degC"
            if got["mean_surface_c"] is None or abs(got["mean_surface_c"] - base["mean_surface_c"]) > 0.5:
                return "mean surface temperature %s instead of %.2f" % (got["mean_surface_c"], base["mean_surface_c"])
    if close:
        return "ok"
    if mutation in PLAUSIBLE and mutation != "truncate_rows":
        # the data changed a little; so may the result, but not beyond what one row can do
        return "ok" if kind != "bdf" or got["rms_v"] < 3 * base["rms_v"] else "RMS %.4g V vs %.4g V" % (got["rms_v"], base["rms_v"])
    if mutation == "truncate_rows":
        return "ok"  # a shorter, valid recording: a different result is the right one
    if REPORTED.search(stderr):
        return "ok"  # accepted, and what was wrong was said
    return "differs from the baseline without a warning (%s)" % json.dumps(got)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "bin"))
    ap.add_argument("--data", default=os.path.join(os.path.dirname(ROOT), "shared", "data", "p45b"))
    ap.add_argument("--count", type=int, default=300)
    ap.add_argument("--timeout", type=float, default=10.0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=16)
    ap.add_argument("--kinds", default="bdf,neware,dewesoft")
    ap.add_argument("--keep", action="store_true", help="keep the mutated files (printed folder)")
    ap.add_argument("--by-mutation", action="store_true", help="also print the outcomes of each mutation")
    args = ap.parse_args()

    cli = os.path.join(args.bin, "cellbench")
    params = os.path.join(ROOT, "config", "cells", "p45b-thesis.json")
    neware_base = os.path.join(args.data, "rw_30degC_neware.csv")
    sources = {"bdf": os.path.join(args.data, "cc_4c_30degC.bdf.csv"), "neware": neware_base,
               "dewesoft": os.path.join(args.data, "rw_30degC_dewesoft.csv")}
    work = tempfile.mkdtemp(prefix="cellbench-mutate-")

    def command(kind, path, out):
        if kind == "bdf":
            return [cli, "simulate", "--params", params, path, "--json", out]
        if kind == "neware":
            return [cli, "import", "--neware", path, "-o", out]
        return [cli, "import", "--neware", neware_base, "--dewesoft", path, "-o", out]

    def out_name(kind, stem):
        return os.path.join(work, stem + (".metrics.json" if kind == "bdf" else ".out.bdf.csv"))

    mutations = sorted(CORRUPTING | PLAUSIBLE)
    table = {}
    failures = []
    for kind in args.kinds.split(","):
        with open(sources[kind], newline="") as f:
            text = f.read()
        base_out = out_name(kind, kind + "-baseline")
        code, so, se, _ = run(command(kind, sources[kind], base_out), 120)
        if code != 0:
            sys.exit("%s baseline failed (%s): %s" % (kind, code, se))
        base = summarize(kind, base_out, so)
        print("%-8s baseline %s" % (kind, json.dumps(base)), flush=True)
        rng = random.Random("%d-%s" % (args.seed, kind))
        jobs = []
        for n in range(args.count):
            mutation = mutations[n % len(mutations)]
            mutated = mutate(text, rng, kind, mutation)
            path = os.path.join(work, "%s-%03d-%s.csv" % (kind, n, mutation))
            with open(path, "wb") as f:
                f.write(mutated if isinstance(mutated, bytes) else mutated.encode())
            jobs.append((n, mutation, path))

        def one(job):
            n, mutation, path = job
            out = out_name(kind, "%s-%03d" % (kind, n))
            code, so, se, secs = run(command(kind, path, out), args.timeout)
            if code is None:
                return mutation, "hang", "over %.0f s" % args.timeout, path
            if code < 0 or code not in (0, 1):
                return mutation, "crash", "status %d: %s" % (code, se[-300:]), path
            if code == 1:
                errors = [l for l in se.splitlines() if l.startswith("error: ")]
                named = len(errors) == 1 and os.path.basename(path) in errors[0]
                if kind == "dewesoft" and len(errors) == 1 and "clock alignment refused" in errors[0]:
                    named = True
                return mutation, "clear error" if named else "unclear error", se.strip()[-300:], path
            try:
                got = summarize(kind, out, so)
            except Exception as e:  # an output we cannot read is wrong too
                return mutation, "SILENT WRONG", "unreadable output: %s" % e, path
            verdict = judge(kind, mutation, base, got, se)
            for p in (out,):
                if os.path.exists(p):
                    os.remove(p)
            return mutation, "success ok" if verdict == "ok" else "SILENT WRONG", verdict, path

        counts = {}
        by_mutation = {}
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as ex:
            for mutation, outcome, detail, path in ex.map(one, jobs):
                counts[outcome] = counts.get(outcome, 0) + 1
                by_mutation.setdefault(mutation, {}).setdefault(outcome, 0)
                by_mutation[mutation][outcome] += 1
                if outcome in ("crash", "hang", "SILENT WRONG", "unclear error"):
                    failures.append((kind, mutation, outcome, detail, path))
                if not args.keep and outcome not in ("crash", "hang", "SILENT WRONG", "unclear error"):
                    os.remove(path)
        table[kind] = counts
        print("%-8s %s" % (kind, json.dumps(counts)), flush=True)
        if args.by_mutation:
            for m in sorted(by_mutation):
                print("    %-18s %s" % (m, json.dumps(by_mutation[m])))

    cols = ["crash", "hang", "clear error", "unclear error", "success ok", "SILENT WRONG"]
    print()
    print("| kind | files | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for kind, counts in table.items():
        print("| %s | %d | " % (kind, sum(counts.values())) + " | ".join(str(counts.get(c, 0)) for c in cols) + " |")
    for kind, mutation, outcome, detail, path in failures[:40]:
        print("%s %s %s: %s (%s)" % (kind, mutation, outcome, detail.replace("\n", " | ")[:300], path))
    print("mutated files kept in" if args.keep or failures else "work folder", work)
    if not args.keep and not failures:
        shutil.rmtree(work, ignore_errors=True)
    bad = sum(c.get("crash", 0) + c.get("hang", 0) + c.get("SILENT WRONG", 0) for c in table.values())
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
