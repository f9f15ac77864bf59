//! `resize-to-deconv`: nearest-neighbour upsampling by an integer factor becomes a depthwise
//! ConvTranspose with a ones kernel, bit-exact; other modes are left, with the reason.

use super::*;

fn resize(input: &str, output: &str, mode: &str) -> NodeProto {
    let mut n = node("Resize", &[input, "", "scales"], output, vec![string_attr("mode", mode), string_attr("coordinate_transformation_mode", "asymmetric")]);
    if mode == "nearest" {
        n.attribute.push(string_attr("nearest_mode", "floor"));
    }
    n
}

#[test]
fn nearest_upsampling_becomes_a_transposed_convolution_bit_for_bit() {
    let mut m = model(
        vec![resize("x", "up", "nearest"), node("Relu", &["up"], "y", vec![]), resize("x", "z", "linear")],
        vec![vi("x", &[1, 2, 3, 4])],
        vec![vi("y", &[1, 2, 6, 8]), vi("z", &[1, 2, 6, 8])],
        vec![init("scales", vec![4], vec![1.0, 1.0, 2.0, 2.0])],
    );
    let inputs = vec![input("x", vec![1, 2, 3, 4], 5)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let r = run_passes(&mut m, "resize-to-deconv");
    let d = &r[0].details;
    assert_eq!(d["replaced"][0]["factors"], serde_json::json!([2, 2]), "{d}");
    assert_eq!(d["left"].as_array().map(Vec::len), Some(1), "the linear Resize is left: {d}");
    assert_eq!(ops(&m), ["ConvTranspose", "Relu", "Resize"]);
    assert_same(&before, &outputs(Engine::Ort, &m, &inputs), 0.0);
}
