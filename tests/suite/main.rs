//! The integration suite: one binary, one module per area (each test binary links tract and
//! ONNX Runtime, so 24 of them cost minutes of linking). `scripts/test --fast` runs the tier
//! that trains nothing and needs no RKNN toolkit; `scripts/test` runs all of it.

mod common;

mod bad_input;
mod bench;
mod coco_map_vs_pycocotools;
mod compile_detect_f32;
mod compile_identity;
mod fuzz_corpus;
mod guide;
mod inspect_fixtures;
mod layers;
mod onnx_node_tests;
mod optics;
mod passes;
mod physics_cli;
mod proto_roundtrip;
mod recipes;
mod records;
mod reference;
mod results;
mod roundtrip_fixtures;
mod run;
mod scene;
mod shape_inference;
mod ship;
mod stress;
mod target_rknn;
mod target_tract;
mod trained_model;
mod user_exports;
mod verify_cli;
