#!/usr/bin/env bash
# The README's promise, checked: on a fresh venv with torch 2.13.0 (CPU), the commands of the README's
# "Install into your own environment" block, run verbatim, give a gsw whose `gsw.embed` works with its
# defaults (LPIPS weights included) on the built-in scene.
#
#   bash .ci/fresh_install.sh                  # in CI after `make test` (.ci/run)
#   bash .ci/fresh_install.sh --print-commands # only print the README block it runs (tests/test_install.py)
#
# Environment: PYTHON (default python3), TORCH_SPEC (default torch==2.13.0+cpu: the CPU build, never a
# CUDA torch), TORCH_INDEX_URL (extra index for TORCH_SPEC, e.g. https://download.pytorch.org/whl/cpu),
# KEEP=1 keeps the temporary folder. Needs access to PyPI. The working tree (tracked and untracked files
# that git does not ignore) is copied, so no build output of the checkout is reused.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
MARKER='<!-- fresh-install:'

readme_commands() {
  # The first ```bash block after the marker comment in the README's install section.
  awk -v marker="$MARKER" '
    index($0, marker) == 1 { armed = 1; next }
    armed && /^```bash$/ { inside = 1; next }
    inside && /^```$/ { exit }
    inside { print }
  ' "$ROOT/README.md"
}

if [[ "${1:-}" == "--print-commands" ]]; then
  readme_commands
  exit 0
fi

COMMANDS="$(readme_commands)"
if [[ -z "$COMMANDS" ]]; then
  echo "fresh_install: no install block after '$MARKER' in README.md" >&2
  exit 1
fi

START=$SECONDS
WORK="$(mktemp -d "${TMPDIR:-/tmp}/gsw-fresh.XXXXXX")"
cleanup() { if [[ "${KEEP:-0}" != 1 ]]; then rm -rf "$WORK"; else echo "kept $WORK"; fi; }
trap cleanup EXIT
step() { echo "== fresh install [$((SECONDS - START)) s]: $*"; }

step "copying the working tree to $WORK/src"
mkdir -p "$WORK/src"
(cd "$ROOT" && git ls-files -z --cached --others --exclude-standard \
  | tar --null --ignore-failed-read -T - -cf - 2>/dev/null) | tar -xf - -C "$WORK/src"

step "fresh venv + ${TORCH_SPEC:=torch==2.13.0+cpu}"
"${PYTHON:-python3}" -m venv "$WORK/venv"
# shellcheck disable=SC1091
source "$WORK/venv/bin/activate"
pip install -q "$TORCH_SPEC" ${TORCH_INDEX_URL:+--extra-index-url "$TORCH_INDEX_URL"}
python -c "import torch; print('torch', torch.__version__, 'CUDA', torch.version.cuda)"

step "the README's install commands, verbatim:"
echo "$COMMANDS"
(cd "$WORK/src" && bash -euxo pipefail -c "$COMMANDS")

step "gsw.embed with its defaults on the built-in scene"
cd "$WORK"  # not the source tree: import the installed gsw
cat > check.py <<'EOF'
import time, gsw
from gsw.mark.embed import paper_config
from gsw.scenes import default_scene
t = time.time()
scene = default_scene(width=64, height=64, n_cameras=4, detail=0.3)  # tiny: a CPU check, not a benchmark
res = gsw.embed(scene.gaussians, scene.cameras, message="key:fresh-install", progress=False)  # the defaults
assert "site-packages" in gsw.__file__ and gsw.build_info()["built_with_torch"] == gsw.build_info()["torch"]
assert res.gaussians.num_gaussians > 0 and min(res.psnr) > 25 and len(res.bit_accuracy) == 4, res.psnr
# the default recipe (a sampled viewpoint every step) needs more steps than this tiny check runs to read the
# embedding views (README); the paper's recipe reads them after 32 steps
paper = gsw.embed(scene.gaussians, scene.cameras, message="key:fresh-install", config=paper_config(),
                  progress=False)
acc = sum(paper.bit_accuracy) / len(paper.bit_accuracy)
print(f"gsw {gsw.__version__}: paper recipe bits {acc:.3f}, PSNR >= {min(paper.psnr):.1f} dB, {time.time() - t:.0f} s; "
      f"{gsw.build_info()}")
assert acc > 0.5 and min(paper.psnr) > 25, (acc, paper.psnr)
EOF
python check.py
step "OK"
