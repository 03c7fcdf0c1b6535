"""Networks. One readable file per model; torch is imported only by the model modules.

    ps_fcn.py    PS-FCN, PS-FCN+N and UPS-FCN (Chen et al., ECCV 2018 / TPAMI 2020)
    weights.py   finding, loading (ours and the authors' ``*.pth.tar``) and saving weights
"""

from __future__ import annotations

# method name -> what the network needs. "normalization" is the default +N variant for the
# method; our own weights files record the variant they were trained with (see weights.py).
NETWORK_METHODS: dict[str, dict] = {
    "ps-fcn": {"lights": True, "normalization": "none"},
    "ps-fcn-n": {"lights": True, "normalization": "per-channel"},
    "ups-fcn": {"lights": False, "normalization": "none"},
}

__all__ = ["NETWORK_METHODS"]
