#!/usr/bin/env python3
"""Converts revisited Oxford/Paris ground truth (gnd_roxford5k.pkl, gnd_rparis6k.pkl; Radenovic et al. 2018)
to JSON that `oxbow eval` reads, using only python3's own pickle module (no numpy needed: numpy arrays in
the pickle are rebuilt as plain lists by a restricted unpickler).

  scripts/revisited_gt_to_json.py ../shared/data/roxford5k/gt/gnd_roxford5k.pkl roxford5k.json
"""
import json
import pickle
import sys


class _Array(list):
    """Stands in for numpy.ndarray when the pickle holds arrays (it rebuilds them from their state)."""

    def __setstate__(self, state):
        # ndarray state: (version, shape, dtype, is_fortran, raw bytes or list)
        data = state[4] if isinstance(state, tuple) and len(state) >= 5 else state
        if isinstance(data, list):
            self.extend(data)
        else:
            raise pickle.UnpicklingError("binary numpy arrays are not supported; re-save with lists")


class _Unpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.startswith("numpy"):
            if name in ("ndarray", "_reconstruct"):
                return lambda *args, **kwargs: _Array()
            if name == "dtype":
                return lambda *args, **kwargs: None
            if name == "scalar":
                return lambda dtype, raw: raw
        if module == "builtins" and name in ("list", "dict", "tuple", "set", "int", "float", "str"):
            return getattr(__import__("builtins"), name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def main(argv):
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    with open(argv[1], "rb") as f:
        data = _Unpickler(f, encoding="latin1").load()
    out = {
        "imlist": list(data["imlist"]),
        "qimlist": list(data["qimlist"]),
        "gnd": [
            {
                "bbx": [float(v) for v in g.get("bbx", [])],
                "easy": [int(v) for v in g.get("easy", [])],
                "hard": [int(v) for v in g.get("hard", [])],
                "junk": [int(v) for v in g.get("junk", [])],
            }
            for g in data["gnd"]
        ],
    }
    with open(argv[2], "w") as f:
        json.dump(out, f)
    print(f"{argv[2]}: {len(out['imlist'])} database images, {len(out['qimlist'])} queries", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
