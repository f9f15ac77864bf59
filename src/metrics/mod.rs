//! Accuracy measures: tensor agreement and COCO-style detection mAP.

pub mod coco_map;
pub mod tensor_error;
