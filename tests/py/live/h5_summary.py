# h5py's view of a motion file: frames, joints, mel frames.
import h5py, json, sys
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"]
    m = f["audio/mel"]
    ok = bool(__import__("numpy").isfinite(j[:]).all())
    print(json.dumps({"frames": j.shape[0], "joints": j.shape[1], "mel": list(m.shape),
                      "finite": ok, "format": f.attrs["format"]}))
