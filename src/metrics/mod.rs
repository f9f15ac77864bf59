//! Accuracy measures: tensor agreement, box error at each box's scale, COCO-style detection
//! mAP, and validation's decode and agreement rules.

pub mod box_error;
pub mod coco_map;
pub mod order;
pub mod validation;
pub mod tensor_error;
