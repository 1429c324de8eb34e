# The package builders' SMPL table (models/packages/pkg_common.py), as JSON.
import json, sys
sys.path.insert(0, sys.argv[1])
import pkg_common as C
print(json.dumps({"parents": C.SMPL_PARENTS, "offsets": C.SMPL_OFFSETS.tolist()}))
