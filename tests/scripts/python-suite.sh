# Sourced by the Python suites' run.sh (tests/python, tests/view, tests/lerobot_plugins): the parts they share.

# py_venv NAME PKG...: the venv ${XDG_CACHE_HOME:-~/.cache}/phone2act/NAME, outside the checkout, created once and
# reused; PKG... are installed on every run (the SDK generates its stubs from proto/ at build time, so a
# reinstall picks up proto edits). Sets VENV.
py_venv() {
  local name=$1
  shift
  VENV="${XDG_CACHE_HOME:-$HOME/.cache}/phone2act/$name"
  if [[ ! -x "$VENV/bin/python" ]]; then
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install -q --upgrade pip
  fi
  "$VENV/bin/pip" install -q "$@"
}

# server_binary: the phone2act binary the suite starts, built by cargo unless PHONE2ACT_BIN is set.
server_binary() {
  if [[ -z "${PHONE2ACT_BIN:-}" ]]; then
    cargo build --release -p phone2act-cli --bin phone2act
    PHONE2ACT_BIN="${CARGO_TARGET_DIR:-$PWD/target}/release/phone2act"
  fi
  export PHONE2ACT_BIN
  export SVT_LOG=1
}
