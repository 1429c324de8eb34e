//! Embeds the three.js modules the viewer's player imports, from the npm package that
//! scripts/setup installs (`npm ci` in assets/viewer, versions pinned by its package-lock.json).
//! Without them the binary still builds; the player then says how to get them.

use std::fmt::Write;
use std::path::PathBuf;

/// Paths under node_modules/ the player loads (three.module.js imports three.core.js; the
/// loader imports BufferGeometryUtils and SkeletonUtils).
const FILES: [&str; 6] = [
    "three/build/three.module.js",
    "three/build/three.core.js",
    "three/examples/jsm/loaders/GLTFLoader.js",
    "three/examples/jsm/utils/BufferGeometryUtils.js",
    "three/examples/jsm/utils/SkeletonUtils.js",
    "three/examples/jsm/controls/OrbitControls.js",
];

fn main() {
    let manifest = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let modules = manifest.join("assets/viewer/node_modules");
    let mut table = String::from(
        "/// three.js modules embedded at build time.\nstatic THREE_FILES: &[(&str, &[u8])] = &[\n",
    );
    let present = FILES.iter().all(|f| modules.join(f).is_file());
    for f in FILES {
        let path = modules.join(f);
        println!("cargo:rerun-if-changed={}", path.display());
        if present {
            writeln!(
                table,
                "    ({f:?}, include_bytes!({:?})),",
                path.display().to_string()
            )
            .expect("write to a String");
        }
    }
    table.push_str("];\n");
    if !present {
        println!(
            "cargo:warning=three.js is not installed in {}: the viewer's player will not load \
             (run scripts/setup, then rebuild)",
            modules.display()
        );
    }
    let out =
        PathBuf::from(std::env::var("OUT_DIR").expect("set by cargo")).join("viewer_vendor.rs");
    std::fs::write(out, table).expect("write OUT_DIR/viewer_vendor.rs");
}
