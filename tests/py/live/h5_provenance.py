# `/provenance` of a motion file as JSON (attributes as strings or numbers).
import h5py, json, sys
with h5py.File(sys.argv[1], "r") as f:
    p = f["provenance"].attrs
    print(json.dumps({k: (v.decode() if isinstance(v, bytes) else v.item() if hasattr(v, "item") else v)
                      for k, v in p.items()}))
