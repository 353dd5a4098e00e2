#!/bin/sh
# A stripped Ray 2.40 for the offline GPU machines (Python 3.12, x86-64; #27), small enough to travel with the
# working tree (~12 MiB): ray_bundle.tar.xz (ray/ + its dist-info) and the jsonschema wheels Ray imports, in OUT.
#
#   sh benchmarks/ray_bundle.sh OUT          (here, with pip access; OUT e.g. .whl-ray, git-ignored)
#   sh OUT/INSTALL.sh                        (there, from the repo root; then PYTHONPATH=/tmp/site)
#
# Kept: Ray core (raylet, gcs_server, _raylet.so, debug symbols stripped), Ray Data, the dashboard package (it
# starts even with include_dashboard=False), pynvml (GPU detection). Removed: RLlib, Serve, Tune, Train, workflows,
# jars, the dashboard's web client, cloud autoscaler providers, bundled copies of aiohttp / psutil / colorama (the GPU image has them), stubs.
# Checked on an H200 machine: ray.init, tasks with num_gpus, a killed worker's retry, Ray Data map_batches.
set -eu
OUT=$(mkdir -p "${1:?OUT}" && cd "$1" && pwd)
W=$(mktemp -d)
PLAT="--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64"
python3 -m pip download -q --no-deps $PLAT -d "$W/dl" ray==2.40.0
# shellcheck disable=SC2086
python3 -m pip download -q --no-deps $PLAT -d "$OUT" jsonschema==4.23.0 referencing==0.35.1 rpds-py==0.22.3 \
  jsonschema-specifications==2024.10.1
mkdir "$W/x" && (cd "$W/x" && python3 -m zipfile -e "$W"/dl/ray-2.40.0-*.whl .)
cd "$W/x/ray"
rm -rf rllib serve tune train workflow jars dashboard/client
for f in _raylet.so core/src/ray/raylet/raylet core/src/ray/gcs/gcs_server core/libjemalloc.so; do
  strip --strip-unneeded "$f"; chmod 0755 "$f"
done
find . -name __pycache__ -prune -exec rm -rf {} +
find . \( -name '*.pyi' -o -name '*.pxd' -o -name '*.pxi' \) -delete
rm -rf _private/runtime_env/agent/thirdparty_files thirdparty_files/colorama* thirdparty_files/psutil* \
  autoscaler/aliyun autoscaler/aws autoscaler/azure autoscaler/gcp autoscaler/spark autoscaler/vsphere \
  autoscaler/_private/_azure autoscaler/_private/aliyun autoscaler/_private/aws autoscaler/_private/gcp \
  autoscaler/_private/kuberay autoscaler/_private/spark autoscaler/_private/vsphere \
  autoscaler/_private/fake_multi_node air/examples util/dask util/spark util/joblib util/horovod util/lightgbm \
  util/xgboost util/sgd data/preprocessors setup-dev.py
cd "$W/x"
python3 - <<'PY'
import base64, hashlib, os
rows = []
for top in ("ray", "ray-2.40.0.dist-info"):
    for d, _, fs in os.walk(top):
        for f in sorted(fs):
            p = os.path.join(d, f)
            if not p.endswith("RECORD"):
                h = base64.urlsafe_b64encode(hashlib.sha256(open(p, "rb").read()).digest()).rstrip(b"=").decode()
                rows.append(f"{p},sha256={h},{os.path.getsize(p)}")
rows.append("ray-2.40.0.dist-info/RECORD,,")
open("ray-2.40.0.dist-info/RECORD", "w").write("\n".join(sorted(rows)) + "\n")
PY
# The three large binaries next to each other in the archive: xz then shares their common code.
BIG="ray/_raylet.so ray/core/src/ray/raylet/raylet ray/core/src/ray/gcs/gcs_server"
# shellcheck disable=SC2086
{ echo $BIG | tr ' ' '\n'; find ray ray-2.40.0.dist-info -type f | grep -v -x -F "$(echo $BIG | tr ' ' '\n')"; } \
  > "$W/list"
tar -cf - -T "$W/list" | xz -9e -T1 > "$OUT/ray_bundle.tar.xz"
cat > "$OUT/INSTALL.sh" <<'SH'
#!/bin/sh
# Ray 2.40.0 offline bundle -> /tmp/site (on the GPU machine; then PYTHONPATH=/tmp/site).
set -e
D=$(dirname "$0")
mkdir -p /tmp/site
tar -xpJf "$D/ray_bundle.tar.xz" -C /tmp/site
"${PYTHON:-python3}" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "$D"/*.whl
chmod 0755 /tmp/site/ray/core/src/ray/raylet/raylet /tmp/site/ray/core/src/ray/gcs/gcs_server
SH
rm -rf "$W"
echo "wrote $OUT: $(du -sh "$OUT" | cut -f1)"
