# Sourced by the other scripts: where the Python environment and ONNX Runtime live.
# C4G_VENV overrides the virtual environment (default: .venv in the repository).
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
C4G_VENV="${C4G_VENV:-$REPO/.venv}"
PYTHON="$C4G_VENV/bin/python"
ORT_VERSION=1.31.1
if [ -z "${ORT_DYLIB_PATH:-}" ] && [ -x "$PYTHON" ]; then
  ORT_DYLIB_PATH="$("$PYTHON" -c 'import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so.'"$ORT_VERSION"'"))' 2>/dev/null || true)"
fi
export REPO C4G_VENV PYTHON ORT_DYLIB_PATH
