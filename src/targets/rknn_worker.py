"""RKNN-Toolkit2's worker, run by `pdi-compile` inside the toolkit's venv.

Reads a job (JSON). `build` (rknn-convert): from the folder's rknn.yaml as JSON, builds the
.rknn file, runs the toolkit's simulator on the validation frames and saves every output as
.npy; its result (with the toolkit's version) is its `done` event. The toolkit's native
library prints its layer placement table to stdout in verbose mode; the caller keeps what
is not an event as the log.
`points` (the rknn-qat pass): the toolkit's quantization points for a model, i.e. every
tensor its step-1 quantization config lists, with its type and parameters.
"""
import ctypes
import json
import os
import sys
from importlib.metadata import version

import numpy as np
from rknn.api import RKNN
from ruamel.yaml import YAML

def ok(code, what):
    if code != 0:
        raise SystemExit(f"rknn-toolkit2 {what} failed (code {code}); see the log above")


def main(job_path):
    with open(job_path) as f:
        job = json.load(f)
    if job.get("mode") == "points":
        return points(job)
    cfg, q = job["config"], job["config"]["quantization"]
    # rknn.yaml's paths are relative to the artifact folder; the working folder is a temp
    # folder, where the toolkit's own dumps (check*.onnx, hybrid step files) land.
    model = os.path.join(job["dir"], cfg["model"])
    dataset = os.path.join(job["dir"], q["dataset"])
    r = RKNN(verbose=True)
    ok(r.config(
        mean_values=cfg["input"]["mean_values"],
        std_values=cfg["input"]["std_values"],
        target_platform=cfg["target_platform"],
        quantized_dtype=q["quantized_dtype"],
        quantized_algorithm=q["quantized_algorithm"],
        quantized_method=q["quantized_method"],
        auto_hybrid_cos_thresh=q["auto_hybrid_cos_thresh"],
    ), "config")
    ok(r.load_onnx(model=model, outputs=cfg["outputs"]), "load_onnx")
    spans = [[l["input"], l["output"]] for l in q.get("fp16_layers", [])]
    trained = dict(q.get("trained_points") or {})
    trained_count = len(trained)
    if cfg["input"].get("range"):
        # The input's int8 range (the toolkit names the quantized input `<input>_int8`).
        lo, hi = cfg["input"]["range"]
        trained[cfg["input"]["name"] + "_int8"] = {"min": lo, "max": hi}
    written = {"set": 0, "absent": []}
    fp16_built = 0
    if q["do_quantization"] and (spans or trained):
        # Hybrid quantization: step 1 writes <model>.model/.data/.quantization.cfg into the
        # working folder with the spans in float16, step 2 builds from them. Trained points
        # (rknn-qat) replace the toolkit's own calibration of those tensors in between.
        ok(r.hybrid_quantization_step1(dataset=dataset, custom_hybrid=spans), "hybrid_quantization_step1")
        stem = os.path.splitext(os.path.basename(cfg["model"]))[0]
        # The toolkit skips (with a warning) a span whose tensors its own graph renamed by fusion.
        with open(f"{stem}.quantization.cfg") as f:
            fp16_built = len(YAML(typ="safe").load(f).get("custom_quantize_layers") or {})
        if trained:
            written = write_points(f"{stem}.quantization.cfg", trained)
        r.release()
        r = RKNN(verbose=True)
        ok(r.hybrid_quantization_step2(model_input=f"{stem}.model", data_input=f"{stem}.data", model_quantization_cfg=f"{stem}.quantization.cfg"), "hybrid_quantization_step2")
    else:
        ok(r.build(do_quantization=q["do_quantization"], dataset=dataset if q["do_quantization"] else None, auto_hybrid=q["auto_hybrid"]), "build")
    ok(r.export_rknn(job["rknn"]), "export_rknn")
    ok(r.init_runtime(), "init_runtime (simulator)")
    for i, path in enumerate(job["frames"]):
        outs = r.inference(inputs=[np.load(path)], data_format="nchw")
        if len(outs) != len(cfg["outputs"]):
            raise SystemExit(f"the simulator returned {len(outs)} outputs; rknn.yaml lists {len(cfg['outputs'])}")
        for name, o in zip(cfg["outputs"], outs):
            np.save(f"{job['out_dir']}/{i:04d}_{name}.npy", np.ascontiguousarray(o, dtype=np.float32))
    r.release()
    done({"toolkit": version("rknn-toolkit2"), "ranges_set": written["set"], "ranges_absent": written["absent"],
          "trained_points": trained_count, "fp16_built": fp16_built})


def write_points(path, trained):
    """Overwrites the ranges of the cfg's entries for the trained points (the toolkit derives
    scale and zero point from them and refuses edits to those); returns how many were set
    and which the toolkit's plan lacks. The file is edited line by line: re-serializing it
    reformats other entries' floats, which the toolkit then takes for edits it refuses."""
    with open(path) as f:
        lines = f.read().split("\n")
    parsed = YAML(typ="safe").load("\n".join(lines))["quantize_parameters"]
    present = [n for n in trained if n in parsed]
    # Entry keys sit at 4 spaces, their fields at 8, list items at "        -   ".
    entry, field = None, None
    for i, line in enumerate(lines):
        if line.startswith("    ") and not line.startswith("     ") and line.rstrip().endswith(":"):
            key = line.strip()[:-1]
            entry = YAML(typ="safe").load(key) if key[:1] in "'\"" else key
            field = None
        elif line.startswith("        ") and not line.startswith("         ") and line.rstrip().endswith(":"):
            field = line.strip()[:-1]
        elif line.startswith("        -   ") and entry in trained and field in ("min", "max"):
            lines[i] = f"        -   {float(trained[entry][field])!r}"
            field = None
    with open(path, "w") as f:
        f.write("\n".join(lines))
    check = YAML(typ="safe").load("\n".join(lines))["quantize_parameters"]
    for n in present:
        for k in ("min", "max"):
            if float(check[n][k][0]) != float(trained[n][k]):
                raise SystemExit(f"could not write the trained {k} of '{n}' into {path}")
    return {"set": len(present), "absent": [n for n in trained if n not in parsed]}


def points(job):
    """The toolkit's quantization points of job["model"], calibrated on job["dataset"]."""
    r = RKNN(verbose=False)
    ok(r.config(mean_values=job["mean_values"], std_values=job["std_values"], target_platform=job["target_platform"],
                quantized_dtype="w8a8", quantized_algorithm="normal", quantized_method="channel"), "config")
    ok(r.load_onnx(model=job["model"], outputs=job["outputs"]), "load_onnx")
    ok(r.hybrid_quantization_step1(dataset=job["dataset"], custom_hybrid=[]), "hybrid_quantization_step1")
    r.release()
    stem = os.path.splitext(os.path.basename(job["model"]))[0]
    with open(f"{stem}.quantization.cfg") as f:
        params = YAML(typ="safe").load(f)["quantize_parameters"]
    out = {}
    for name, p in params.items():
        one = lambda k: p[k][0] if isinstance(p.get(k), list) and p[k] else None
        out[name] = {"dtype": p["dtype"], "min": one("min"), "max": one("max"), "scale": one("scale"), "zero_point": one("zero_point")}
    done({"toolkit": version("rknn-toolkit2"), "points": out})


def done(result):
    """The result, as a line of its own on stdout (the workers' protocol: `pyenv::run_python`).
    The toolkit's native library writes to the same descriptor through C's buffers: those go
    first, and the line starts fresh."""
    sys.stdout.flush()
    ctypes.CDLL(None).fflush(None)
    print("\n" + json.dumps(dict(result, event="done")), flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
