# Shared by the GPU scripts (sourced): the wheels and the packed scene sets, installed and unpacked once per
# machine, so that two scripts started side by side (or one after the other on a warm machine) share them.
# A marker beside each target says it is complete; a target without one is (re)made.
gpu_packages() {  # gpu_packages WHEEL_DIR LOG
    [ -f /tmp/pk.done ] && return 0
    python3 -m pip install -q --no-deps --target /tmp/pk "$1"/*.whl >> "$2" 2>&1 && touch /tmp/pk.done
}
gpu_unpack() {  # gpu_unpack PACKED OUT_DIR LOG
    [ -f "$2.done" ] && return 0
    python3 benchmarks/scene_pack.py unpack "$1" "$2" >> "$3" 2>&1 && touch "$2.done"
}
