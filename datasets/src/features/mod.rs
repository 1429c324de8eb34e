//! Motion features: HumanML3D's 263-dim representation, style-transfer inputs built from any
//! motion file, and long content cut into overlapping segments.

pub mod humanml3d;
pub mod motion_input;
pub mod segments;
