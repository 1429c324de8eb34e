//! Motion a person can look at: GIF / PNG pictures of the skeleton, and glTF (a skinned
//! mannequin made here, the skeleton, one animation).

pub mod gltf;
pub mod mannequin;
pub mod picture;
