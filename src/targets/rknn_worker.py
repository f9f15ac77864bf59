"""rknn-convert's worker, run by `pdi-compile rknn-convert` inside the RKNN-Toolkit2 venv.

Reads a job (JSON: the folder's rknn.yaml as JSON, frame paths, where to write), builds the
.rknn file, runs the toolkit's simulator on the validation frames and saves every output as
.npy; writes a result JSON with the toolkit's version. The toolkit's native library prints
its layer placement table to stdout in verbose mode; the caller keeps stdout as the log.
"""
import json
import os
import sys
from importlib.metadata import version

import numpy as np
from rknn.api import RKNN

def ok(code, what):
    if code != 0:
        raise SystemExit(f"rknn-toolkit2 {what} failed (code {code}); see the log above")


def main(job_path):
    with open(job_path) as f:
        job = json.load(f)
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
    if q["do_quantization"] and spans:
        # Hybrid quantization: step 1 writes <model>.model/.data/.quantization.cfg into the
        # working folder with the spans in float16, step 2 builds from them.
        ok(r.hybrid_quantization_step1(dataset=dataset, custom_hybrid=spans), "hybrid_quantization_step1")
        stem = os.path.splitext(os.path.basename(cfg["model"]))[0]
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
    with open(job["result"], "w") as f:
        json.dump({"toolkit": version("rknn-toolkit2")}, f)


if __name__ == "__main__":
    main(sys.argv[1])
