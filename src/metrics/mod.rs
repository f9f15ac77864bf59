//! Accuracy measures: tensor agreement, COCO-style detection mAP, and validation's decode
//! and agreement rules.

pub mod coco_map;
pub mod order;
pub mod validation;
pub mod tensor_error;
