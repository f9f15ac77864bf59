//! `bind-psf`: the PALS-Bridge's blur map, a graph input or a baked constant, becomes an
//! initializer holding the camera's map from `--psf`; the model computes what the original
//! computes when fed that map.

use super::*;
use crate::common::{inputs_for, load};
use pdi_compile::onnx::tensor_proto::to_tensor;
use pdi_compile::optics::npy;

const PSF: &str = "calib/radial_6x8.npy";

fn bind(fixture: &str) -> (ModelProto, ModelProto, serde_json::Value) {
    let original = load(&repo().join("models/fixtures").join(fixture));
    let mut m = original.clone();
    let mut cx = PassContext { psf: Some(repo().join(PSF)), ..Default::default() };
    let r = run_with(&mut m, "bind-psf", &mut cx);
    (original, m, r[0].details.clone())
}

#[test]
fn an_input_map_becomes_the_files_constant_and_computes_the_same() {
    let (original, bound, d) = bind("pdinet_v5_input_op17_fold.onnx");
    assert_eq!(d["maps"][0]["was"], "input", "{d}");
    let g = bound.graph.as_ref().unwrap();
    assert!(!g.input.iter().any(|v| v.name == "psf_blur"), "the map left the interface");
    let file = npy::read(&repo().join(PSF)).unwrap();
    let map = to_tensor(g.initializer.iter().find(|t| t.name == "psf_blur").expect("the map is an initializer")).unwrap();
    assert_eq!(map.shape, [1, 1, 6, 8]);
    assert_eq!(map.as_f32().unwrap(), &file.data[..]);
    // The original fed the file's map, the bound model fed only the image: the same bits.
    let fed: Vec<(String, Tensor)> = inputs_for(&original, 6).into_iter().map(|(n, t)| if n == "psf_blur" { (n, map.clone()) } else { (n, t) }).collect();
    let image: Vec<(String, Tensor)> = fed.iter().filter(|(n, _)| n != "psf_blur").cloned().collect();
    assert_same(&outputs(Engine::Ort, &original, &fed), &outputs(Engine::Ort, &bound, &image), 0.0);
}

#[test]
fn a_baked_map_is_replaced_by_the_file() {
    let (_, bound, d) = bind("pdinet_v8_const_op13_nofold.onnx");
    assert_ne!(d["maps"][0]["was"], "input", "{d}");
    let file = npy::read(&repo().join(PSF)).unwrap();
    let name = d["maps"][0]["name"].as_str().unwrap();
    let g = bound.graph.as_ref().unwrap();
    let map = to_tensor(g.initializer.iter().find(|t| t.name == name).unwrap()).unwrap();
    assert_eq!(map.as_f32().unwrap(), &file.data[..]);
    assert!(!g.node.iter().any(|n| n.op_type == "Constant" && n.output[0] == name), "the baked Constant is gone");
}
