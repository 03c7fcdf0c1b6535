#!/usr/bin/env bash
# Regenerates the pictures in docs/img/ (README's "Pictures") with psctl's own commands, from the
# DiLiGenT dev split in ../shared/data (not part of a clone). About 4 minutes on a 2-core CPU.
#   bash docs/img/make_pictures.sh [DATA_ROOT]
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=${1:-../shared/data/diligent/pmsData_crop}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
psctl eval -b diligent --root "$ROOT" -m l2,ensemble -o "$TMP/eval" -q
psctl lights "$ROOT/catPNG" -o "$TMP/lights" -q
psctl depth "$ROOT/catPNG" --normals "$TMP/eval/ensemble/cat/normal.png" -o "$TMP/depth" -q
# recompressed at zlib level 9 (psctl writes level 4, for speed): the same pixels, smaller files
python - "$TMP" <<'PY'
import sys
import OpenImageIO as oiio
tmp = sys.argv[1]
for src, dst in ((f"{tmp}/eval/compare.png", "docs/img/dev_split_l2_vs_ensemble.png"),
                 (f"{tmp}/lights/lights.png", "docs/img/cat_lights.png"),
                 (f"{tmp}/depth/shading.png", "docs/img/cat_depth_shading.png")):
    buf = oiio.ImageBuf(src)
    buf.specmod().attribute("png:compressionLevel", 9)
    assert buf.write(dst), buf.geterror()
    print("wrote", dst)
PY
