# Source on the lent GPU machine, from the repository root: `. tools/gpu_device_setup.sh [CARRY]`.
# Installs what tools/gpu_carry.py packed into CARRY (default .gpu-carry): the wheels into
# /tmp/site, Mitsuba into a folder of its own (tools/gpu_unpack.py replaces the folder it
# unpacks into), the scenes into /tmp/scenes; then exports PYTHONPATH and PACKETRT_SCENE_PATH
# and prints the GPU and the versions python3 now imports.
carry="${1:-.gpu-carry}"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    "$carry"/whl/*.whl || return 2
if [ -f "$carry/mitsuba.zip" ]; then
    python3 tools/gpu_unpack.py "$carry/mitsuba.zip" /tmp/mitsuba >/dev/null || echo "gpu_device_setup: Mitsuba not unpacked"
fi
if [ -f "$carry/scenes.zip" ]; then
    python3 -c "import sys, zipfile; zipfile.ZipFile(sys.argv[1]).extractall('/tmp/scenes')" "$carry/scenes.zip"
fi
export PYTHONPATH="/tmp/site:/tmp/mitsuba:$PWD" PACKETRT_SCENE_PATH=/tmp/scenes PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -c "import numpy, numba, numba.cuda as c; print('numpy', numpy.__version__, 'numba', numba.__version__, 'cuda', c.is_available())"
