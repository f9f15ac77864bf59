"""Small seeds for the fuzz corpus that the fixtures cannot give at a fuzzable size.

Run by scripts/fuzz with the cache's Python (onnx, numpy, PIL): a few tiny ONNX models
(a convolution with BatchNorm and a sigmoid, a Reshape/Concat/Split chain, external data
pointing outside the folder, a Constant-node weight), and frames in each format the loader
reads (8/16-bit, RGB, TIFF, .npy). Writes into the folder given as the first argument.
"""
import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from PIL import Image

out = sys.argv[1]


def save(target, name, data):
    os.makedirs(os.path.join(out, target), exist_ok=True)
    with open(os.path.join(out, target, name), "wb") as f:
        f.write(data)


def model(nodes, inits, inputs, outputs, opset=13):
    g = helper.make_graph(nodes, "seed", inputs, outputs, initializer=inits)
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)]).SerializeToString()


x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, 8, 8])
w = numpy_helper.from_array(np.ones((4, 1, 3, 3), np.float32) / 9, "w")
bn = [numpy_helper.from_array(np.full(4, v, np.float32), n) for n, v in [("s", 1.0), ("b", 0.0), ("m", 0.1), ("v", 1.0)]]
y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])
save("onnx", "conv_bn_sigmoid.onnx", model(
    [helper.make_node("Conv", ["image", "w"], ["c"], pads=[1, 1, 1, 1]),
     helper.make_node("BatchNormalization", ["c", "s", "b", "m", "v"], ["n"]),
     helper.make_node("Sigmoid", ["n"], ["y"])], [w] + bn, [x], [y]))
shape = numpy_helper.from_array(np.array([1, 2, 32], np.int64), "shape")
split = numpy_helper.from_array(np.array([1, 1], np.int64), "split")
z = helper.make_tensor_value_info("z", TensorProto.FLOAT, None)
save("onnx", "reshape_concat_split.onnx", model(
    [helper.make_node("Reshape", ["image", "shape"], ["r"]),
     helper.make_node("Split", ["r", "split"], ["a", "b"], axis=1),
     helper.make_node("Concat", ["b", "a"], ["z"], axis=1)], [shape, split], [x], [z], opset=17))
ext = onnx.TensorProto(name="w", data_type=TensorProto.FLOAT, dims=[4, 1, 3, 3], data_location=TensorProto.EXTERNAL)
ext.external_data.add(key="location", value="../../../etc/passwd")
save("onnx", "external_escape.onnx", model([helper.make_node("Conv", ["image", "w"], ["y"], pads=[1, 1, 1, 1])], [ext], [x], [y]))
const = helper.make_node("Constant", [], ["w"], value=numpy_helper.from_array(np.ones((4, 1, 3, 3), np.float32), "wc"))
save("onnx", "constant_weight.onnx", model([const, helper.make_node("Conv", ["image", "w"], ["y"], pads=[1, 1, 1, 1])], [], [x], [y]))

ramp = np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)
for name, img in [("gray8.png", Image.fromarray((ramp * 255).astype(np.uint8))),
                  ("gray16.png", Image.fromarray((ramp * 65535).astype(np.uint16))),
                  ("rgb.png", Image.fromarray(np.stack([(ramp * 255).astype(np.uint8)] * 3, -1)))]:
    path = os.path.join(out, "image", name)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    img.save(path)
Image.fromarray((ramp * 255).astype(np.uint8)).save(os.path.join(out, "image", "gray8.tif"))
os.makedirs(os.path.join(out, "npy"), exist_ok=True)
np.save(os.path.join(out, "npy", "frame.npy"), ramp)
np.save(os.path.join(out, "npy", "f64.npy"), ramp.astype(np.float64))
