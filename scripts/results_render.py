"""Renders docs/results/records/*.json into the README's results table, the demo's screen and
the docs/results pages' record blocks. Nothing here measures: every figure comes from a record.

A page holds a record's block between `<!-- record NAME -->` and `<!-- /record NAME -->`
(added at the page's end the first time); the README holds `<!-- results table -->` and
`<!-- demo screen -->` blocks the same way.
"""
import hashlib
import json
import re
import statistics
import sys
from collections import Counter
from pathlib import Path

RECORDS = "docs/results/records"


def load(root):
    recs = {}
    for p in sorted((root / RECORDS).glob("*.json")):
        r = json.loads(p.read_text())
        recs[r["name"]] = r
    return recs


# --- words and numbers -----------------------------------------------------------------------

def cpu(m):
    return f"{m['cpu']}{' (AVX-512)' if m.get('avx512') else ''}"


def machine(m):
    s = f"{m['cores']}-core {cpu(m)}, {m['threads']} threads"
    return s + (f", GPU {m['gpu']}" if m.get("gpu") else ", no GPU")


def megs(n):
    return f"{n / 1e6:.0f} M" if n >= 1e7 else f"{n / 1e6:.1f} M"


def size(b):
    return f"{b / 1e6:.2f} MB" if b >= 1e6 else f"{b / 1e3:.1f} kB"


def dur(s):
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min"


def f4(x):
    return "-" if x is None else f"{x:.4f}"


def table(head, rows):
    out = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


# --- which recipes a record ran, and whether they still ship --------------------------------

def computes(text):
    """What a recipe computes: its base, what it leaves out of the base and its passes; not
    its name or description, whose wording changes no byte."""
    head = [l for l in text.splitlines() if l.startswith(("base:", "without:"))]
    return "\n".join(head) + (text[text.index("\npasses:"):] if "\npasses:" in text else text)


def digests(texts):
    """Recipe name -> digest of what it computes, for recipe texts by name."""
    return {n: hashlib.sha256(computes(x).encode()).hexdigest()[:16] for n, x in sorted(texts.items())
            if x.startswith("name:")}


def shipped(root):
    """The recipes in the checkout at `root`, by name: their texts."""
    return {p.stem: p.read_text() for p in sorted((root / "passes").glob("*.yaml"))}


# Recipes a command runs without naming a file: `ship` compiles its variants from these (the
# last one's own passes only, on the pruned variant).
SHIP = (["detect-f32", "detect-pruned-rknn"], ["detect-pruned-int8"])
IMPLIED = {"pdi-compile ship": SHIP, "scripts/demo": SHIP}


def used(r, texts):
    """The recipes record `r` compiled with: whole (with their bases) or their own passes alone."""
    whole, own = set(), set()
    for c in r["commands"]:
        cmd = c["command"]
        whole |= set(re.findall(r"(?:passes|recipes)/([a-z0-9-]+)\.yaml", cmd))
        own |= set(re.findall(r"/([a-z0-9-]+?)-own[.-]", cmd))
        for k, (w, o) in IMPLIED.items():
            if k in cmd:
                whole |= set(w)
                own |= set(o)
    if "direction" in r["figures"] or "change" in r["figures"]:
        whole.add("detect-pruned-f32")  # each direction is that recipe with one change
    todo, out = sorted(whole & texts.keys()), own & texts.keys()
    while todo:
        n = todo.pop()
        out.add(n)
        todo += [b for b in re.findall(r"^base: ([a-z0-9-]+)$", texts[n], re.M) if b in texts and b not in out]
    return sorted(out)


def changed_since(r, texts, now):
    """The recipes `r` ran that compute something else now (records without their recipes'
    digests: none known)."""
    then = r.get("recipes")
    return [] if then is None else [n for n in used(r, texts) if then.get(n) != now.get(n)]


# --- one block per record --------------------------------------------------------------------

def lossless(f):
    return table(["model", "MACs: original → compiled", "mAP original", "mAP compiled", "agreement", "worst rel L2"],
                 [[m["model"], f"{megs(m['macs_original'])} → {megs(m['macs'])}", f4(m["map_reference"]),
                   f4(m["map"]), f4(m["agreement"]), f"{m['rel_l2']:.1e}"] for m in f["models"]])


def int8(f):
    return table(["model", "mAP original", "mAP INT8", "kept", "agreement", "worst rel L2", "error budget"],
                 [[m["model"], f4(m["map_reference"]), f4(m["map"]), f"{m['map'] / m['map_reference']:.3f}×",
                   f4(m["agreement"]), f"{m['rel_l2']:.3f}", "missed" if m["missed_budget"] else "met"]
                  for m in f["models"]])


def int8_options(f):
    rows = [[r["model"], r["option"], f4(r["map_reference"]), f4(r["map"]), f"{r['map'] - r['map_reference']:+.4f}",
             f4(r["agreement"]), f"{r['rel_l2']:.3f}", str(r["float_layers"])] for r in f["rows"]]
    return ["`detect-int8` as shipped and with one option changed, on the 200 held-out frames:", ""] + \
        table(["model", "detect-int8", "mAP original", "mAP INT8", "change", "agreement", "worst rel L2", "layers kept float"], rows)


def int8_regions(f):
    rows = [[r["model"], r["form"], str(r["nodes_float"]), f4(r["map_reference"]), f4(r["map"]),
             f"{r['map'] - r['map_reference']:+.4f}", f4(r["agreement"]), f"{r['rel_l2']:.3f}"] for r in f["rows"]]
    return ["`detect-int8` with one region of the network kept float (`keep_float`: every node of it), on the 200 "
            "held-out frames, calibration seed 0:", ""] + \
        table(["model", "detect-int8", "nodes kept float", "mAP original", "mAP INT8", "change", "agreement", "worst rel L2"], rows)


def int8_seeds(f):
    rows = []
    for m in dict.fromkeys(r["model"] for r in f["rows"]):
        for form in dict.fromkeys(r["form"] for r in f["rows"]):
            rs = [r for r in f["rows"] if r["model"] == m and r["form"] == form]
            ch = [r["map"] - r["map_reference"] for r in rs]
            rows.append([m, form, f4(rs[0]["map_reference"]), " / ".join(f"{c:+.4f}" for c in ch),
                         f"{sum(ch) / len(ch):+.4f}", f"{max(ch) - min(ch):.4f}",
                         f"{sum(r['agreement'] for r in rs) / len(rs):.4f}", f"{max(r['rel_l2'] for r in rs):.3f}"])
    seeds = ", ".join(str(s) for s in dict.fromkeys(r["seed"] for r in f["rows"]))
    return [f"`detect-int8` in each form below, calibrated on the simulated frames of seeds {seeds}; mAP@0.5:0.95 "
            f"on the 200 held-out frames:", ""] + \
        table(["model", "form", "mAP original", "change, seed by seed", "mean change", "spread", "mean agreement",
               "worst rel L2"], rows)


def variants(vs):
    rows = []
    for v in vs:
        ms = lambda k: "-" if v[k] is None else f"{v[k]:.2f}"
        agree = " / ".join("-" if v[k] is None else f"{v[k]:.3f}" for k in ("agreement", "agreement_tract"))
        rows.append([v["name"], size(v["bytes"]), megs(v["macs"]), ms("ort_ms"), ms("tract_ms"), f4(v["map_labels"]),
                     "1.000" if v["name"] == "original" else agree])
    return table(["variant", "size", "MACs", "ORT ms", "tract ms", "mAP (labels)", "agreement ORT / tract"], rows)


def recommended(f):
    return "; ".join(f"{r['target']}: {r['variant'] or 'none'}" for r in f["recommended"])


def demo(f):
    return variants(f["variants"]) + \
        ["", f"Recommended: {recommended(f)}. Recovery: {f['recover_steps']} steps; the demo took {dur(f['seconds'])}."]


def run(f):
    return [f"Artifact: {f['artifact']}.", ""] + table(
        ["engine", "threads", "frames/s", "pre-process ms", "inference ms", "decode + NMS ms", "mAP (labels)"],
        [[e["engine"], e["threads"], f"{e['frames_per_second']:.1f}", f"{e['preprocess_ms']:.2f}",
          f"{e['inference_ms']:.2f}", f"{e['decode_nms_ms']:.2f}", f4(e["map"])] for e in f["engines"]])


def rknn(f):
    r = f["report"]
    rows = [[o["name"], f"{o['cosine']:.4f}", f"{o['rel_l2']:.4f}"] for o in r["outputs"] + r["groups"]]
    cpu = ", ".join(r["cpu_layers"]) or "none"
    return [f"Artifact: {f['artifact']}; {r['npu_layers']} layers on the NPU, on the CPU: {cpu}. The toolkit's "
            f"simulator against ONNX Runtime ({r['validation']}); detections: {r['detections_matched']} of ONNX Runtime's "
            f"{r['detections_ort']} found (the simulator made {r['detections_rknn']}); "
            f"{'passed' if r['passed'] else 'failed: ' + '; '.join(r['failures'])} at cosine ≥ {r['min_cosine']}:", ""] + \
        table(["output or score group", "cosine", "rel L2"], rows)


def scene(f):
    return table(["model", "ROI", "MACs", "params", "agreement"],
                 [[f["model"], f["roi"], f"{f['macs_ratio']:.3f}×", f"{f['params_ratio']:.3f}×", f4(f["agreement"])]])


def rebuild(f):
    return table(["the demo's folder", "same bytes", "rebuild said"],
                 [[r["variant"], "yes" if r["identical"] else "no", r["said"].replace("|", "\\|")] for r in f["folders"]])


def recipe_bytes(f):
    prev = f.get("previous")
    rows = [[f"`{k}`", f"`{v[:16]}`", "" if not prev else "same" if k in prev["same"] else "differs" if k in prev["differ"] else "new"]
            for k, v in sorted(f["sha256"].items())]
    lines = table(["recipe", "sha256 of model.onnx", f"against commit {prev['commit'][:10]}" if prev else "previous record"], rows)
    return lines + ["", f"Every shipped recipe compiled on the trained {f['model']}, each training shortened to "
                        f"{f['training_steps']} steps (and 64 frames) so that the whole set takes minutes: the "
                        "passes and code paths of the shipped recipes, compared by bytes with the record this one "
                        "replaced."]


def suite(f):
    return table(["`scripts/test` on a fresh clone", "exit", "tests passed", "failed", "the integration suite"],
                 [[dur(f["seconds"]) + " (its build from nothing included)", str(f["exit"]), str(f["passed"]),
                   str(f["failed"]), dur(f["slowest_binary_seconds"])]]) + \
        ["", "The clone's own build; the cache's Python environments (ONNX Runtime, the toolkit's venv) "
             "already installed, Cargo's registry downloaded. A fresh CI machine also downloads the toolkit's "
             "venv, beside the build."]


def broken_builds(f):
    return table(["claim broken on purpose", "file", "test", "the test failed"],
                 [[c["broken"], f"`{c['file']}`", f"`{c['test']}`", "yes" if c["failed"] else "NO"] for c in f["cases"]]) + \
        ["", "Each row: the file edited to break the claim, the test run alone on that build "
             "(`cargo test --test suite -- --exact TEST`), the tree restored; on the unbroken tree the suite "
             "passes every one of them."]


def pruned(f):
    rc = f["recover"]
    capped = ", stopped by its time cap" if rc["capped"] else ""
    busy = f", GPU {rc['gpu_busy_share']:.0%} busy" if rc.get("gpu_busy_share") else ""
    return table(["model", "MACs", "recovery", "mAP original", "pruned f32", "pruned INT8"],
                 [[f["model"], f"{f['macs_ratio']:.2f}×",
                   f"{rc['steps']} steps on the {f['device'].upper()} in {dur(rc['seconds'])} "
                   f"({rc['frames_per_second']:.1f} frames/s{busy}{capped})",
                   f4(f["map_original"]), f"{f4(f['map_f32'])} ({f['kept_f32']:.3f}×)",
                   f"{f4(f['map_int8'])} ({f['kept_int8']:.3f}×)"]]) + \
        ["", "INT8 is `detect-pruned-int8`'s own passes (its quantization) run on the pruned f32 model: the "
             "same bytes as the whole recipe, which starts from `detect-pruned-f32` (the suite checks this), "
             "without training the same model twice."]


def averaged(f):
    a, b, rc = f["average"], f["baseline"], f["recover"]
    rows = [["last step (the shipped recipe's record" + (f", commit {b['commit'][:10]})" if b else ")"),
             f4(a["held_out_loss_last"]), "-" if not b else f"{f4(b['map_f32'])} ({b['kept_f32']:.3f}×)"],
            [f"average, decay {a['decay']}", f4(a["held_out_loss_average"]),
             f"{f4(f['map_f32'])} ({f['kept_f32']:.3f}×)" if a["kept"] else "not kept"]]
    same = b is not None and abs(b["held_out_loss_after"] - a["held_out_loss_last"]) < 1e-9
    return [f"`detect-pruned-f32` on the {f['model']} with `ema: {a['decay']}` in its recovery ({rc['steps']} steps, "
            f"{dur(rc['seconds'])}); the held-out rule kept {'the average' if a['kept'] else 'the last step'}:", ""] + \
        table(["weights", "held-out distillation loss", "mAP@0.5:0.95 (of the original's)"], rows) + \
        ["", "The last step's weights are the shipped recipe's: " + (
            "its held-out loss is the record's to the last digit." if same else
            "its held-out loss differs from the record's (another machine or trainer), so the rows compare less directly.")]


def kept(x):
    """The pruned f32 and INT8 cells of a direction or its baseline: mAP (share of the original's)."""
    return [f"{f4(x['map_f32'])} ({x['kept_f32']:.3f}×)", f"{f4(x['map_int8'])} ({x['kept_int8']:.3f}×)"]


def against(f, b):
    """The lines saying what a direction gained over its baseline record `b` (none without one)."""
    return [] if not b else ["", f"Against the record: f32 {f['kept_f32'] - b['kept_f32']:+.3f}, INT8 "
                                 f"{f['kept_int8'] - b['kept_int8']:+.3f} of the original's mAP."]


def direction(f):
    b, rs = f["baseline"], f["recover"]
    steps = " + ".join(f"{r['steps']}" for r in rs)
    secs = sum(r["seconds"] for r in rs)
    what = f"record `{b['name']}`" if b and b.get("name") else "the shipped recipe's record"
    rows = [[what + (f" (commit {b['commit'][:10]})" if b else "")] + (kept(b) if b else ["-", "-"]),
            [f"{f['direction']} ({f['macs_ratio']:.3f}× MACs)"] + kept(f)]
    return [f"`detect-pruned-f32` on the {f['model']} with one change: {f['change']}. Recovery: {steps} steps in "
            f"{dur(secs)}; mAP@0.5:0.95 of the original's ({f4(f['map_original'])}):", ""] + \
        table(["recipe", "pruned f32", "pruned INT8"], rows) + against(f, b)


def seen(rc):
    """What a recovery's steps saw: crops, or whole frames (with how many a step, where recorded)."""
    if rc.get("crop"):
        return f"{rc['crop']} crops"
    return "whole frames" + (f", {rc['batch']} a step" if rc.get("batch") else "")


def elsewhere(f):
    rc, b = f["recover"], f.get("baseline")
    what = f"`detect-pruned-f32` with one change, {f['change']}," if "change" in f else "The shipped pruned recipes"
    rows = [[f["model"], f"{f['macs_ratio']:.2f}×", f4(f["map_original"])] + kept(f)]
    if b:
        rows.append([f"the shipped recipes' record (commit {b['commit'][:10]})", "", ""] + kept(b))
    return [f"{what} on the {f['model']}, given only unlabelled frames: {f['calibration']} "
            f"({f['calib_frames']} in the folder, {f['frames']} of them held in training; no labels read). Recovery: "
            f"{rc['steps']} steps on {seen(rc)} in {dur(rc['seconds'])} "
            f"({rc['frames_per_second']:.1f} frames/s); mAP@0.5:0.95 on the labelled held-out scenes at 640×480:", ""] + \
        table(["model", "MACs", "mAP original", "pruned f32", "pruned INT8"], rows) + against(f, b)


def camera(f):
    rows = []
    for m in f["models"]:
        t = m["tuned"]
        rows.append([m["model"], f4(m["map_256"]), f"{f4(m['map_640'])} ({f4(m['map50_640'])})",
                     f"{f4(t['seed2'])} ({f4(t['seed2_50'])})", f4(t["card"]),
                     f"{f4(t['seed3'])} ({f4(t['seed3_50'])}), {t['seed3'] - t['card']:+.4f}"])
    t = f["models"][0]["tuned"]
    return table(["model", "at 256×192", "256×192 weights at 640×480", "fine-tuned at 640×480", "its card",
                  "another seed's scenes, against the card"], rows) + \
        ["", f"mAP@0.5:0.95 (mAP@0.5); {f['models'][0]['frames']} frames each. Fine-tuned: {t['epochs']} epochs on "
             f"{t['crop']} crops of 640×480 frames ({t['minutes']:.0f} min on {t['device']}, `models/finetune-640.sh`)."]


def pruned_640(f):
    rc, small = f["recover"], f["at_256"]
    lines = table(["model", "MACs", "recovery", "mAP original", "pruned f32", "compile", "at 256×192"],
                  [[f["model"], f"{f['macs_ratio']:.2f}×",
                    f"{rc['steps']} steps on {seen(rc)} in {dur(rc['seconds'])} ({rc['frames_per_second']:.1f} frames/s)",
                    f4(f["map_original"]), f"{f4(f['map_f32'])} ({f['kept_f32']:.3f}×)", dur(f["compile_seconds"]),
                    "-" if not small else f"{dur(small['compile_seconds'])} ({f['compile_seconds'] / small['compile_seconds']:.2f}× here)"]])
    lines += ["", f"The same recipe with {f['short'][0]['steps']} recovery steps, on crops and on whole frames:", ""]
    lines += table(["frames", "recovery", "frames/s", "pruned f32 mAP", "kept"],
                   [[s["crop"] if s["crop"] != "none" else "whole 640×480" + (f", {s['batch']} a step" if s.get("batch") else ""), dur(s["seconds"]), f"{s['frames_per_second']:.1f}",
                     f4(s["map"]), f"{s['kept']:.3f}×"] for s in f["short"]])
    return lines


def ship_640(f):
    return [f"`ship` on the {f['model']}, {f['recover_steps']} recovery steps, on the held-out scenes at 640×480:", ""] + \
        variants(f["variants"]) + ["", f"Recommended: {recommended(f)}."]


def goal_median(figures, v):
    """Variant `v`'s median ratio over a latency record's goal loops."""
    return statistics.median(loop[v] for loop in figures["goals"]["loops"])


def goal_loops(f, goals):
    """The goal lines read off a latency record's short loops of the goal's models alone:
    `goals` holds (variant, shown as, [(bound, why)]); the verdict is the median's, the range
    shows the drift between loops run back to back."""
    g = f.get("goals")
    if not g:
        return []
    parts = []
    for v, shown, bounds in goals:
        xs = sorted(loop[v] for loop in g["loops"])
        med = goal_median(f, v)
        verdicts = "; ".join(f"goal ≤ {b}{why}: {'met' if med <= b else 'not met'}" for b, why in bounds)
        parts.append(f"`{shown}` {med:.3f}× ({xs[0]:.3f}–{xs[-1]:.3f}; {verdicts})")
    return ["", f"The goals' models alone, in {len(g['loops'])} short interleaved loops run back to back after it "
                f"(ONNX Runtime, {g['threads']} threads, {g['runs']} runs each), against `detect-f32`: the median of the "
                f"loops (their range): " + "; ".join(parts) + "."]


def latency(f):
    by = {(r["variant"], r["engine"]): r for r in f["rows"]}
    rows = []
    for r in f["rows"]:
        top = ", ".join(f"{o['op']} {o['share']:.0%}" for o in r["ops"][:3])
        rows.append([f"`{r['variant']}`: {r['what']}", r["engine"], f"{r['median_ms']:.2f}", f"{r['ratio']:.3f}×",
                     f"{r['macs_ratio']:.3f}×", f"{r['gmacs_per_s']:.1f} ({r['best_gmacs_per_s']:.1f})", top])
    out = table(["variant", "engine", "ms", "against f32", "MACs", "GMAC/s (best layer)", "top operators"], rows)
    o = lambda v: by[(v, "ort")]["ratio"]
    t = lambda v: by[(v, "tract")]["median_ms"] / by[(v, "ort")]["median_ms"]
    head = lambda v: f", {o(v + '-head'):.3f}× with the last convolutions' inputs quantized" if (v + "-head", "ort") in by else ""
    out += ["", f"On ONNX Runtime, against `detect-f32`: `detect-int8` {o('int8'):.3f}× (goal ≤ 0.8; "
                f"{o('int8-all'):.3f}× with `narrow_float: 0`{head('int8')}), "
                f"`detect-pruned-f32` {o('pruned-f32'):.3f}× at {by[('pruned-f32', 'ort')]['macs_ratio']:.3f}× the MACs "
                f"(goal ≤ 1.5× its MAC ratio), `detect-pruned-int8` {o('pruned-int8'):.3f}× (goal ≤ 0.5; "
                f"{o('pruned-int8-all'):.3f}× without `narrow_float`{head('pruned-int8')})"
                + ". tract against ONNX Runtime: "
                + ", ".join(f"`{v}` {t(v):.2f}×" for v in ("f32", "pruned-f32", "int8", "pruned-int8")) + "."]
    if ("pruned-f32-2d", "ort") in by:
        # narrow-convs-nchw's gain, within the same loop: each model against itself in 2-D.
        pairs = [("pruned-f32", "pruned-f32-2d"), ("pruned-int8", "pruned-int8-2d"), ("int8", "int8-2d"), ("f32-3d", "f32")]
        out[-1] += (" `narrow-convs-nchw` on ONNX Runtime, each model against its 2-D form: " + ", ".join(
            f"`{a}` {by[(a, 'ort')]['median_ms'] / by[(b, 'ort')]['median_ms']:.3f}× of `{b}`" for a, b in pairs) + ".")
    if ("pruned-f32-bias", "ort") in by:
        # narrow-convs-nchw's two forms, each pruned model against itself in 3-D, in the long
        # loop and as the median of the goal loops.
        loops = f.get("goals", {}).get("loops", [])
        out[-1] += (" `narrow-convs-nchw` with `form: bias` on ONNX Runtime, each pruned model against its 3-D form: " + ", ".join(
            f"`{v}-bias` {by[(v + '-bias', 'ort')]['median_ms'] / by[(v, 'ort')]['median_ms']:.3f}×"
            + (f" ({goal_median(f, v + '-bias') / goal_median(f, v):.3f}× in the goal loops' medians)" if loops and v + "-bias" in loops[0] else "")
            for v in ("pruned-f32", "pruned-int8")) + ".")
    if ("int8-no-s2d", "ort") in by:
        # space-to-depth's gain, within the same loop.
        pairs = [("int8", "int8-no-s2d"), ("pruned-int8", "pruned-int8-no-s2d"), ("f32-s2d", "f32"), ("pruned-f32-s2d", "pruned-f32")]
        out[-1] += (" `space-to-depth` on ONNX Runtime, each model against its form without it: " + ", ".join(
            f"`{a}` {by[(a, 'ort')]['median_ms'] / by[(b, 'ort')]['median_ms']:.3f}× of `{b}`" for a, b in pairs)
            + f"; on tract, `int8` {by[('int8', 'tract')]['median_ms'] / by[('int8-no-s2d', 'tract')]['median_ms']:.3f}× of `int8-no-s2d`.")
    shipped = [v for v in ("f32", "pruned-f32") if (f"{v}-tract", "tract") in by]
    if shipped:
        # What a tract deployment runs (`--target tract`) against ONNX Runtime on the plain model.
        out[-1] += (" In the forms `--target tract` ships, against ONNX Runtime on the plain models: " + ", ".join(
            f"`{v}` {by[(v + '-tract', 'tract')]['median_ms'] / by[(v, 'ort')]['median_ms']:.2f}×" for v in shipped) + ".")
        for v in shipped:
            forms = f["tract_forms"][f"{v}-tract"]
            tiled = [c["node"] for c in forms["conv_tiles"] if c["tiled"]]
            bands = [d for d in forms["depthwise_split"] if "reason" not in d]
            out += ["", f"`{v}-tract`: {len(bands)} depthwise convolution(s) split into bands, "
                        f"{len(tiled)} of {len(forms['conv_tiles'])} direct convolutions shipped as column tiles"
                        + (f" ({', '.join(f'`{n}`' for n in tiled)})" if tiled else "")
                        + f"; fastest on {forms['fastest_threads']} thread(s)."]
    gaps = f.get("gaps", [])
    if any(g["variant"].endswith("-tract") for g in gaps):
        gaps = [g for g in gaps if g["variant"].endswith("-tract")]
    for g in gaps:
        out += ["", f"Where tract loses on `{g['variant']}` (layers joined by the model node each engine ran): kernels "
                    f"{g['tract_kernel_ms']:.2f} ms against ONNX Runtime's {g['ort_kernel_ms']:.2f}; in kernels with no "
                    f"counterpart, tract {g['tract_only_ms']:.2f} ms, ONNX Runtime {g['ort_only_ms']:.2f} ms (its layout "
                    "reorders and fused activations).", ""]
        out += table(["layers tract runs as", "layers", "tract ms", "ONNX Runtime ms", "tract − ONNX Runtime"],
                     [[o["op"], str(o["layers"]), f"{o['tract_ms']:.2f}", f"{o['ort_ms']:.2f}", f"{o['tract_ms'] - o['ort_ms']:+.2f}"]
                      for o in g["by_tract_op"]])
        out += ["", "The layers it loses most on: " + "; ".join(
            f"`{l['node']}` {l['tract_ms']:.2f} ms ({l['tract_op']}) against {l['ort_ms']:.2f}" for l in g["layers"]) + "."]
    mac = by[("pruned-f32", "ort")]["macs_ratio"]
    out += goal_loops(f, [("int8", "detect-int8", [(0.8, "")]), ("pruned-int8", "detect-pruned-int8", [(0.5, "")]),
                          ("pruned-f32", "detect-pruned-f32", [(round(1.5 * mac, 3), f", 1.5× its MAC ratio of {mac:.3f}"),
                                                               (0.42, ", 1.5× a MAC ratio of 0.28")])])
    slow = [(l["node"], l["ms"], l.get("gmacs_per_s")) for l in by[("pruned-int8", "ort")]["layers"][:3]]
    out += ["", "The slowest layers of `pruned-int8` on ONNX Runtime: " + "; ".join(
        f"`{n}` {ms:.2f} ms" + (f" ({g:.1f} GMAC/s)" if g else "") for n, ms, g in slow) + "."]
    return out


def latency_256(f):
    rows = [[f"`{r['variant']}`: {r['what']}", r["engine"], f"{r['median_ms']:.2f}", f"{r['ratio']:.3f}×",
             ", ".join(f"{o['op']} {o['share']:.0%}" for o in r["ops"][:3])] for r in f["rows"]]
    by = {(r["variant"], r["engine"]): r for r in f["rows"]}
    return [f"{f['model']}, {f['runs']} interleaved runs on {f['threads']} threads:", ""] + \
        table(["variant", "engine", "ms", "against f32", "top operators"], rows) + \
        ["", f"On ONNX Runtime `detect-int8` runs at {by[('int8', 'ort')]['ratio']:.3f}× of `detect-f32` "
             f"(goal: no slower, ≤ 1), without its 3-D convolutions at {by[('int8-2d', 'ort')]['ratio']:.3f}×, "
             + (f"without `space-to-depth` (the recipe before) at {by[('int8-no-s2d', 'ort')]['ratio']:.3f}×, "
                if ("int8-no-s2d", "ort") in by else "") +
             f"with `narrow_float: 0` at {by[('int8-all', 'ort')]['ratio']:.3f}×"
             + (f", and with its last convolutions' inputs quantized (the recipe before) at {by[('int8-head', 'ort')]['ratio']:.3f}×"
                if ("int8-head", "ort") in by else "")
             + (f"; with each SiLU float between the integer convolutions at {by[('int8-silu', 'ort')]['ratio']:.3f}×"
                if ("int8-silu", "ort") in by else "") + "."] + goal_loops(f, [("int8", "detect-int8", [(1, ", no slower")])])


def latency_640_full(f):
    rows = [[f"`{r['variant']}`: {r['what']}", r["engine"], f"{r['median_ms']:.1f}", f"{r['ratio']:.3f}×", f"{r['macs_ratio']:.3f}×",
             ", ".join(f"{o['op']} {o['share']:.0%}" for o in r["ops"])] for r in f["rows"]]
    by = {(r["variant"], r["engine"]): r for r in f["rows"]}
    o = lambda v: by[(v, "ort")]["ratio"]
    t = lambda v: by[(v, "tract")]["median_ms"] / by[(v, "ort")]["median_ms"]
    noise = "; ".join(f"`{n['variant']}` ({n['lifted']} convolution(s) in 3-D) {n['rel_l2']:.1e}" for n in f["narrow_convs_nchw"])
    return [f"{f['model']}, {f['runs']} interleaved runs on {f['threads']} threads:", ""] + \
        table(["variant", "engine", "ms", "against f32", "MACs", "top operators"], rows) + \
        ["", f"On ONNX Runtime, against `detect-f32`: `detect-int8` {o('int8'):.3f}× (goal ≤ 0.45), `detect-pruned-f32` "
             f"{o('pruned-f32'):.3f}× at {by[('pruned-f32', 'ort')]['macs_ratio']:.3f}× the MACs, `detect-pruned-int8` "
             f"{o('pruned-int8'):.3f}×. tract against ONNX Runtime: `f32` {t('f32'):.2f}×, `pruned-f32` {t('pruned-f32'):.2f}×. "
             f"The 3-D form against the 2-D one on ONNX Runtime (rel L2 on 4 synthetic frames): {noise}."] + \
        goal_loops(f, [("int8", "detect-int8", [(0.45, "")])])


def tract_kernels(f):
    rows = [[f"`{r['file']}`", f"{r['op']} {r['channels']} channels at {r['width']}×{r['height']}, "
             + ", ".join(f"{k} {v}" for k, v in r["attributes"].items()),
             f"{r['macs'] / 1e6:.1f} M" if r["macs"] else "-", r["tract_kernels"], f"{r['tract_ms']:.2f}", f"{r['ort_ms']:.2f}",
             f"{r['tract_ms'] / r['ort_ms']:.2f}×"] for r in f["rows"]]
    return [f"Each layer alone after a 1×1 convolution from the 640×480 frame (random weights), both engines in one "
            f"interleaved loop ({f['runs']} runs, {f['threads']} threads), the layer's own time from each engine's profile:", ""] + \
        table(["model", "layer", "MACs", "tract kernels", "tract ms", "ONNX Runtime ms", "tract / ONNX Runtime"], rows)


BLOCKS = {"lossless": lossless, "latency-640": latency, "latency-640-full": latency_640_full, "tract-kernels": tract_kernels, "latency-256": latency_256, "camera-640": camera, "pruned-640": pruned_640,
          "elsewhere-v5": elsewhere, "elsewhere-v8": elsewhere,
          "ship-640-v5": ship_640, "ship-640-v8": ship_640, "int8": int8, "int8-options": int8_options, "int8-seeds": int8_seeds, "int8-regions": int8_regions, "demo": demo, "run": run, "rknn": rknn, "scene": scene,
          "rebuild": rebuild, "recipe-bytes": recipe_bytes,
          "broken-builds": broken_builds, "suite": suite}


def ort_ratios(figures):
    """Each variant's latency against `detect-f32` on ONNX Runtime, from a latency record."""
    out = {r["variant"]: round(r["ratio"], 3) for r in figures.get("rows", []) if r.get("engine") == "ort"}
    loops = figures.get("goals", {}).get("loops", [])
    for v in (loops[0] if loops else {}):
        out[f"goal:{v}"] = round(goal_median(figures, v), 3)
    return out


# The ratios a latency record's history table shows, in this order, where a loop measured them.
HISTORY_COLUMNS = {
    "latency-640": ["int8", "int8-no-s2d", "int8-head", "pruned-f32", "pruned-int8", "pruned-int8-no-s2d",
                    "pruned-f32-round16", "pruned-f32-round8", "pruned-f32-latency",
                    "goal:int8", "goal:pruned-f32", "goal:pruned-int8"],
    "latency-256": ["int8", "int8-no-s2d", "int8-2d", "int8-head", "int8-silu", "goal:int8"],
    "latency-640-full": ["int8", "pruned-f32", "pruned-int8", "goal:int8"],
}


def history(r):
    """Every loop the record has run in, this one last: the recipes as they were at each commit."""
    runs = r["history"] + [{"commit": r["commit"], "date": r["date"], "machine": r["machine"],
                            "figures": ort_ratios(r["figures"])}]
    cols = [c for c in HISTORY_COLUMNS[r["name"]] if any(c in h["figures"] for h in runs)]
    return [f"Every run of this record, against `detect-f32` on ONNX Runtime (the recipes as they were at each "
            f"commit; the CPU's drift moves a ratio by up to a third from run to run):", ""] + \
        table(["date", "commit", "CPU"] + [f"`{c[5:]}` (goal loops)" if c.startswith("goal:") else f"`{c}`" for c in cols],
              [[h["date"], h["commit"][:7], cpu(h["machine"])]
               + [f"{h['figures'][c]:.3f}×" if c in h["figures"] else "-" for c in cols] for h in runs])


def block(r, stale=()):
    fn = BLOCKS.get(r["name"]) or (pruned if r["name"].startswith("pruned-") else averaged if r["name"].startswith("ema-")
                                   else elsewhere if r["name"].startswith("elsewhere-")
                                   else direction if "direction" in r["figures"] else None)
    commit = r["commit"][:10] + (" (with uncommitted changes to the product)" if r["commit_has_changes"] else "")
    load = r["machine"].get("load_before")
    lines = [f"**Record `{r['name']}`** ({r['tier']} tier of `scripts/results`): {r['date']}, {machine(r['machine'])}"
             f"{f', load {load} at the start' if load is not None else ''}; commit {commit}; {dur(r['seconds'])}.", ""]
    if stale:
        lines += [f"Recipes changed since this run (their passes or options, at commit {r['commit'][:10]} against "
                  f"the checkout): {', '.join(f'`{n}`' for n in stale)}. Its figures are those recipes' as they were.", ""]
    rep = r.get("repeat")
    if rep:
        same = rep["compared"] - len(rep["differ"])
        lines += [f"Against the record it replaced (commit {rep['commit'][:10]}, the same CPU): {same} of "
                  f"{rep['compared']} figures other than times the same" +
                  ("." if not rep["differ"] else "; differ: " + ", ".join(
                      f"`{d['figure']}` {d['before']} → {d['now']}" for d in rep["differ"][:8]) +
                   (f" and {len(rep['differ']) - 8} more" if len(rep["differ"]) > 8 else "") + "."), ""]
    lines += fn(r["figures"])
    if r.get("history"):
        lines += [""] + history(r)
    lines += ["", "Commands (from the repository root; seconds):", ""]
    lines += [f"- `{c['command']}` ({c['seconds']:.0f} s)" for c in r["commands"]]
    return lines


# --- the README ------------------------------------------------------------------------------

def readme_rows(recs):
    rows = []

    def row(task, result, name, page):
        rows.append((task, result, name, page))

    if "lossless" in recs:
        ms = recs["lossless"]["figures"]["models"]
        same = all(abs(m["map"] - m["map_reference"]) < 5e-5 for m in ms)
        t = next(m for m in ms if m["model"] == "v5 tiny")
        row("lossless compile (`detect-f32`)",
            f"{'the same mAP' if same else 'mAP moved'} on the {len(ms)} trained models (tiny v5: {f4(t['map_reference'])} → "
            f"{f4(t['map'])}); outputs within {max(m['rel_l2'] for m in ms):.0e} rel L2; tiny v5 {megs(t['macs_original'])} → "
            f"{megs(t['macs'])} MACs", "lossless", "demo.md")
    cpu = [recs[n] for n in ("pruned-v5-w0.25", "pruned-v8-w0.25") if n in recs]
    # The shipped recipe again with another recovery seed (direction `seedN`): one seed's
    # figure alone reads as more certain than it is.
    reseeded = [recs[n] for n in sorted(recs) if re.fullmatch(r"seed\d+-v[58]-w0\.25", n)]

    def seeds(key):
        return "".join(f"; with recovery's seed {r['figures']['direction'][4:]}: {r['figures'][key]:.3f}× ({r['figures']['model']})"
                       for r in reseeded)
    if cpu:
        fs = [r["figures"] for r in cpu]
        names = [r["name"] for r in cpu + reseeded]
        steps = " / ".join(str(f["recover"]["steps"]) for f in fs)
        took = " / ".join(dur(f["recover"]["seconds"]) for f in fs)
        row(f"prune + recover (`detect-pruned-f32` as shipped: {steps} steps on the CPU, recovery {took})",
            f"{fs[0]['macs_ratio']:.0%} of the MACs; keeps "
            + " and ".join(f"{f['kept_f32']:.3f}× ({f['model']}: {f['map_f32']:.3f} of {f['map_original']:.3f})" for f in fs)
            + " of the mAP" + seeds("kept_f32"), names, "pruning.md")
        row("+ INT8 (`detect-pruned-int8`)",
            "keeps " + " and ".join(f"{f['kept_int8']:.3f}× ({f['model']})" for f in fs) + seeds("kept_int8"), names,
            "pruning.md")
    gpu = [recs[n] for n in ("pruned-v5-w0.25-gpu", "pruned-v8-w0.25-gpu") if n in recs]
    if gpu:
        fs = [r["figures"] for r in gpu]
        row(f"`detect-pruned-f32` as shipped on a GPU ({gpu[0]['machine']['gpu']})",
            "recovery in " + " / ".join(f"{dur(f['recover']['seconds'])} ({f['model']})" for f in fs)
            + "; keeps " + " / ".join(f"{f['kept_f32']:.3f}×" for f in fs), [r["name"] for r in gpu], "pruning.md")
    if "camera-640" in recs:
        ms = recs["camera-640"]["figures"]["models"]
        row("the width-0.25 models fine-tuned at the camera's 640×480 (on 256×192 crops)",
            "mAP " + "; ".join(f"{m['model']}: {f4(m['tuned']['seed2'])} (the 256×192 weights there: {f4(m['map_640'])})" for m in ms)
            + " on the held-out scenes at 640×480", "camera-640", "camera.md")
    if "pruned-640" in recs:
        f = recs["pruned-640"]["figures"]
        row("`detect-pruned-f32` as shipped at 640×480 (v5 w0.25, recovery on crops, CPU)",
            f"{f['macs_ratio']:.0%} of the MACs; keeps {f['kept_f32']:.3f}× ({f['map_f32']:.3f} of {f['map_original']:.3f}); "
            f"compile {dur(f['compile_seconds'])}" + ("" if not f["at_256"] else f" ({f['compile_seconds'] / f['at_256']['compile_seconds']:.2f}× the 256×192 model's)"),
            "pruned-640", "camera.md")
    away = [recs[n] for n in ("elsewhere-v5", "elsewhere-v8") if n in recs]
    if away:
        fs = [r["figures"] for r in away]
        row(f"`detect-pruned-f32` / `-int8` on models trained elsewhere (the 640×480 models, given "
            f"{fs[0]['calib_frames']} unlabelled frames of other scenes)",
            "keeps " + "; ".join(f"{f['kept_f32']:.3f}× / {f['kept_int8']:.3f}× ({f['model'].split(' at ')[0]}, "
                                 f"{f['macs_ratio']:.2f}× the MACs)" for f in fs),
            [r["name"] for r in away], "pruning.md")
    for name in ("ship-640-v5", "ship-640-v8"):
        if name in recs:
            f = recs[name]["figures"]
            v = {x["name"]: x for x in f["variants"]}
            o = v["original"]
            rec = {r["target"]: r["variant"] for r in f["recommended"]}
            row(f"`ship` at 640×480 ({f['model'].split(' at ')[0]}, {f['recover_steps']} recovery steps)",
                "; ".join(f"{n} {x['ort_ms']:.1f} ms ORT / {x['tract_ms']:.1f} ms tract, mAP {f4(x['map_labels'])}"
                          for n, x in v.items() if n != "original" and x.get("ort_ms") is not None)
                + f" (original {o['ort_ms']:.1f} ms, {f4(o['map_labels'])}); recommended for ONNX Runtime: "
                  f"{rec.get('onnxruntime') or 'none'}", name, "camera.md")
    if "latency-640" in recs:
        f = recs["latency-640"]["figures"]
        by = {(r["variant"], r["engine"]): r for r in f["rows"]}
        goal = ort_ratios(f)
        # The goal loops' medians where the record has them, else its one long loop.
        o = lambda v: goal.get(f"goal:{v}", goal[v])
        row("CPU latency at 640×480 (v5 w0.25, ONNX Runtime, against `detect-f32`"
            + (f"; the median of {len(f['goals']['loops'])} short loops" if "goals" in f else "") + ")",
            f"`detect-int8` {o('int8'):.2f}×; `detect-pruned-f32` {o('pruned-f32'):.2f}× at "
            f"{by[('pruned-f32', 'ort')]['macs_ratio']:.2f}× the MACs; `detect-pruned-int8` {o('pruned-int8'):.2f}×; "
            f"tract {by[('f32', 'tract')]['median_ms'] / by[('f32', 'ort')]['median_ms']:.1f}× "
            "ONNX Runtime on `detect-f32`", "latency-640", "latency.md")
    if "int8" in recs:
        ms = recs["int8"]["figures"]["models"]
        row("INT8 without pruning (`detect-int8`)",
            "keeps " + ", ".join(f"{m['map'] / m['map_reference']:.3f}× ({m['model']})" for m in ms), "int8", "quantization.md")
    if "demo" in recs:
        f = recs["demo"]["figures"]
        v = {x["name"]: x for x in f["variants"]}
        p, o = v["pruned-f32"], v["original"]
        row(f"`scripts/demo` (`ship` on the tiny v5, {f['recover_steps']} recovery steps)",
            f"pruned to {p['macs'] / v['f32']['macs']:.0%} of the lossless MACs, keeps {p['map_labels'] / o['map_labels']:.2f}× "
            f"of the mAP; ONNX Runtime {p['ort_ms']:.2f} ms against the original's {o['ort_ms']:.2f}", "demo", "demo.md")
    if "rknn" in recs:
        r = recs["rknn"]["figures"]["report"]
        worst = min(o["cosine"] for o in r["outputs"])
        row("RK3588 (the demo's `rknn` folder, `rknn-convert`)",
            f"{r['npu_layers']} layers on the NPU, {len(r['cpu_layers'])} on the CPU; the toolkit's simulator against ONNX "
            f"Runtime: cosine ≥ {worst:.4f} on every output, {r['detections_matched']} of {r['detections_ort']} detections found", "rknn", "rknn.md")
    if "scene" in recs:
        f = recs["scene"]["figures"]
        row(f"scene: an ROI of {f['roi'].split(', ')[-1]}",
            f"{f['macs_ratio']:.2f}× the MACs at {f['agreement']:.3f} agreement with the full model ({f['model']})",
            "scene", "scene.md")
    if "run" in recs:
        e = {x["engine"]: x for x in recs["run"]["figures"]["engines"]}
        row("`run` end to end (the demo's pruned tiny v5)",
            f"{e['ort']['frames_per_second']:.0f} frames/s on ONNX Runtime, {e['tract']['frames_per_second']:.0f} on tract; "
            f"decode + NMS {e['ort']['decode_nms_ms']:.2f} ms", "run", "run.md")
    if "rebuild" in recs:
        fs = recs["rebuild"]["figures"]["folders"]
        row("reproducible builds (`rebuild` of the demo's folders)",
            f"{sum(r['identical'] for r in fs)} of {len(fs)} rebuilt to the same bytes", "rebuild", "reproducible-builds.md")
    if "suite" in recs:
        f = recs["suite"]["figures"]
        row("the test suite (`scripts/test` on a fresh clone, its build included)",
            f"{dur(f['seconds'])}, {f['passed']} tests passed, {f['failed']} failed", "suite", "tests.md")
    if "broken-builds" in recs:
        cs = recs["broken-builds"]["figures"]["cases"]
        row("tests against broken builds of their claims",
            f"{sum(c['failed'] for c in cs)} of {len(cs)} fail as they must", "broken-builds", "tests.md")
    return rows


def readme_table(recs, texts, now):
    if not recs:
        return ["No records yet: `scripts/results` makes them."]
    machines = Counter(machine(r["machine"]) for r in recs.values())
    common = machines.most_common(1)[0][0]
    dates = sorted(r["date"] for r in recs.values())
    lines = [f"Rendered from `docs/results/records/` (`scripts/results`); measured on a {common} "
             f"({dates[0]}{' to ' + dates[-1] if dates[-1] != dates[0] else ''}) unless a row says otherwise; "
             "mAP@0.5:0.95 against the labels of 200 held-out frames of `scripts/eval-set`:", ""]
    rows = []
    for task, result, names, page in readme_rows(recs):
        # A row may read several records (one per model): each one's date, machine and
        # recipes count, not only the first's.
        rs = [recs[n] for n in ([names] if isinstance(names, str) else names)]
        dates = " / ".join(dict.fromkeys(r["date"] for r in rs))
        where = "".join(f"; {m}" for m in dict.fromkeys(machine(r["machine"]) for r in rs) if m != common)
        stale = {r["name"]: changed_since(r, texts, now) for r in rs}
        lists = {tuple(s) for s in stale.values()}
        # Every record stale the same way: said once; otherwise each stale record by name.
        named = {"": next(iter(lists))} if len(lists) == 1 else stale
        since = "".join(f" ({'`' + n + '`: ' if n else ''}recipe changed since: {', '.join(f'`{x}`' for x in s)})"
                        for n, s in named.items() if s)
        rows.append([task, result, f"[{dates}{where}](docs/results/{page}){since}"])
    return lines + table(["task", "result", "record"], rows)


def demo_screen(recs):
    if "demo" not in recs:
        return ["No demo record yet: `scripts/results --only demo` makes it."]
    r = recs["demo"]
    return [f"Its screen (stderr and stdout, {len(r['figures']['screen'])} lines; {r['date']}, {machine(r['machine'])}; "
            f"[the record](docs/results/demo.md)):", "", "```"] + r["figures"]["screen"] + ["```"]


# --- pages -----------------------------------------------------------------------------------

def splice(text, tag, body, name=None):
    """Replaces the block between <!-- tag --> and <!-- /tag -->, or appends it."""
    open_, close = f"<!-- {tag} -->", f"<!-- /{tag} -->"
    new = "\n".join([open_, *body, close])
    pat = re.compile(re.escape(open_) + r".*?" + re.escape(close), re.S)
    if pat.search(text):
        return pat.sub(lambda _: new, text, count=1)
    heading = "" if "\n## Records\n" in text else "\n## Records\n\nRendered from `docs/results/records/` by `scripts/results`.\n"
    return text.rstrip("\n") + "\n" + heading + "\n" + new + "\n"


def rendered(root):
    recs = load(root)
    texts = shipped(root)
    now = digests(texts)
    pages = {}
    readme = (root / "README.md").read_text()
    readme = splice(readme, "results table", readme_table(recs, texts, now))
    readme = splice(readme, "demo screen", demo_screen(recs))
    pages["README.md"] = readme
    for r in recs.values():
        path = f"docs/results/{r['page']}"
        text = pages.get(path) or (root / path).read_text()
        pages[path] = splice(text, f"record {r['name']}", block(r, changed_since(r, texts, now)))
    return pages


def write(root):
    for path, text in rendered(root).items():
        if (root / path).read_text() != text:
            (root / path).write_text(text)
            print(f"results: rendered {path}", file=sys.stderr)


def check(root):
    stale = [p for p, t in rendered(root).items() if (root / p).read_text() != t]
    for p in stale:
        print(f"results: {p} differs from its records; run scripts/results render", file=sys.stderr)
    return 1 if stale else 0
