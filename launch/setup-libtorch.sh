#!/usr/bin/env bash
# Assemble a CPU-only libtorch for tch 0.26 (which expects PyTorch 2.13.0) out of
# the PyPI wheels, and point <repo>/.libtorch at it (.cargo/config.toml sets
# LIBTORCH to that path).
#
# The torch wheel is CUDA-enabled, but a CPU build only needs a few of its files:
#   include/                 torch/include from the wheel
#   lib/libtorch_cpu.so      }
#   lib/libc10.so            } from torch/lib
#   lib/libtorch.so          } (patched: its DT_NEEDED on libtorch_cuda.so is removed)
#   lib/libgomp.so.1         OpenMP runtime shipped in the wheel (+ libgomp.so for -lgomp)
#   lib/libcudart.so.13      libtorch_cpu.so lists these two as DT_NEEDED even on CPU,
#   lib/libcupti.so.13       so they come from two small nvidia wheels
# libtorch_cuda.so (and cuDNN, cuBLAS, NCCL, ...) is never copied.
#
# Usage: launch/setup-libtorch.sh [-q|--quiet]
# Env:   BCAL_CACHE   cache dir (default ~/.cache/bcal); wheels go to $BCAL_CACHE/wheels
#                     and the tree to $BCAL_CACHE/libtorch-2.13.0.
# Idempotent: a stamp file makes reruns instant. Needs python3 (with pip), readelf, ldd.
set -euo pipefail

TORCH_VERSION=2.13.0
CUDART_SPEC='nvidia-cuda-runtime==13.0.96.*'
CUPTI_SPEC='nvidia-cuda-cupti==13.0.85.*'
# Bump when the assembly below changes: an existing tree with another stamp is rebuilt.
RECIPE="bcal-libtorch recipe 1: torch ${TORCH_VERSION}, ${CUDART_SPEC}, ${CUPTI_SPEC}"

QUIET=0
case "${1:-}" in
  -q|--quiet) QUIET=1 ;;
  "") ;;
  *) echo "usage: $0 [-q|--quiet]" >&2; exit 2 ;;
esac

# -q only silences the "already done" path: once there is work, it is reported.
say() { if [[ $QUIET == 0 ]]; then echo "setup-libtorch: $*" >&2; fi; }
die() { echo "setup-libtorch: error: $*" >&2; exit 1; }

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CACHE=${BCAL_CACHE:-$HOME/.cache/bcal}
WHEELS=$CACHE/wheels
DEST=$CACHE/libtorch-$TORCH_VERSION
STAMP=$DEST/.bcal-stamp
LINK=$REPO/.libtorch

link_repo() {
  if [[ -e $LINK && ! -L $LINK ]]; then
    die "$LINK exists and is not a symlink; move it away"
  fi
  if [[ "$(readlink "$LINK" 2>/dev/null || true)" != "$DEST" ]]; then
    ln -sfn "$DEST" "$LINK"
    say "linked $LINK -> $DEST"
  else
    say "$LINK -> $DEST (ok)"
  fi
}

# Fast path: already assembled by this recipe.
if [[ -f $STAMP && "$(cat "$STAMP")" == "$RECIPE" ]]; then
  say "libtorch $TORCH_VERSION already assembled in $DEST"
  link_repo
  exit 0
fi

mkdir -p "$WHEELS"
# Serialise concurrent runs (two checkouts sharing one cache).
if command -v flock >/dev/null; then
  exec 9>"$CACHE/.setup-libtorch.lock"
  flock 9
  if [[ -f $STAMP && "$(cat "$STAMP")" == "$RECIPE" ]]; then
    say "libtorch $TORCH_VERSION assembled meanwhile by another run"
    link_repo
    exit 0
  fi
fi

QUIET=0
for tool in python3 readelf ldd; do
  command -v "$tool" >/dev/null || die "$tool not found"
done

# --- 1. wheels --------------------------------------------------------------
# The wheels are zip files; download for a fixed target (CPython 3.11, manylinux
# x86_64) so that this works whatever python3 this machine has.
PIP_DOWNLOAD=(python3 -m pip download --no-deps --only-binary=:all:
  --python-version 3.11 --implementation cp
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
  --platform manylinux_2_25_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64
  -d "$WHEELS")

find_wheel() {  # $1: glob inside $WHEELS; prints the newest match or nothing
  local f
  f=$(ls -1t "$WHEELS"/$1 2>/dev/null | head -n 1 || true)
  [[ -n $f ]] && echo "$f"
  return 0
}

fetch_wheel() {  # $1: glob of the wheel file, $2: pip requirement
  local whl
  whl=$(find_wheel "$1")
  if [[ -z $whl ]]; then
    say "downloading $2 into $WHEELS"
    "${PIP_DOWNLOAD[@]}" "$2" >&2
    whl=$(find_wheel "$1")
    [[ -n $whl ]] || die "pip did not produce a wheel matching $1"
  else
    say "using cached $(basename "$whl")"
  fi
  echo "$whl"
}

TORCH_WHL=$(fetch_wheel "torch-${TORCH_VERSION}-cp311-cp311-manylinux*_x86_64.whl" "torch==${TORCH_VERSION}")
CUDART_WHL=$(fetch_wheel "nvidia_cuda_runtime-13.0.96*-py3-none-*x86_64*.whl" "$CUDART_SPEC")
CUPTI_WHL=$(fetch_wheel "nvidia_cuda_cupti-13.0.85*-py3-none-*x86_64*.whl" "$CUPTI_SPEC")

# --- 2. assemble into a scratch dir, then move into place -------------------
TMP=$(mktemp -d "$CACHE/libtorch-${TORCH_VERSION}.tmp.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
say "assembling in $TMP"

python3 - "$TMP" "$TORCH_WHL" "$CUDART_WHL" "$CUPTI_WHL" <<'PY'
import os, re, shutil, sys, zipfile

out, torch_whl, cudart_whl, cupti_whl = sys.argv[1:]
inc, lib = os.path.join(out, "include"), os.path.join(out, "lib")
os.makedirs(inc)
os.makedirs(lib)

def copy_member(z, info, dest):
    os.makedirs(os.path.dirname(dest), exist_ok=True)
    with z.open(info) as src, open(dest, "wb") as dst:
        shutil.copyfileobj(src, dst, 1 << 20)

with zipfile.ZipFile(torch_whl) as z:
    n_inc = 0
    wanted = {"libtorch_cpu.so", "libc10.so", "libtorch.so"}
    gomp = None
    for info in z.infolist():
        name = info.filename
        if name.endswith("/"):
            continue
        if name.startswith("torch/include/"):
            copy_member(z, info, os.path.join(inc, name[len("torch/include/"):]))
            n_inc += 1
        elif name.startswith("torch/lib/") and os.path.basename(name) in wanted:
            copy_member(z, info, os.path.join(lib, os.path.basename(name)))
            wanted.discard(os.path.basename(name))
        elif re.fullmatch(r"torch(/lib|\.libs)/libgomp[^/]*\.so[.0-9]*", name):
            gomp = info
    if wanted:
        sys.exit(f"missing in torch wheel: {sorted(wanted)}")
    if gomp is None:
        sys.exit("no libgomp in torch wheel")
    # Stored under its own file name; the shell renames it to the soname
    # libtorch_cpu.so asks for.
    copy_member(z, gomp, os.path.join(lib, "gomp-from-wheel"))
    print(f"  include/: {n_inc} files; lib/: libtorch_cpu.so libc10.so libtorch.so; "
          f"gomp from {gomp.filename}")
    ver = z.read("torch/version.py").decode()
    m = re.search(r"__version__\s*=\s*'([^']+)'", ver)
    with open(os.path.join(out, "build-version"), "w") as f:
        f.write(m.group(1).split("+")[0] + "\n")   # torch-sys checks this file

for whl, stem in ((cudart_whl, "libcudart.so"), (cupti_whl, "libcupti.so")):
    with zipfile.ZipFile(whl) as z:
        hits = [i for i in z.infolist()
                if re.fullmatch(r"nvidia/[^/]+/lib/" + re.escape(stem) + r"\.[0-9]+", i.filename)]
        if len(hits) != 1:
            sys.exit(f"expected one {stem}.N in {whl}, found {[i.filename for i in hits]}")
        copy_member(z, hits[0], os.path.join(lib, os.path.basename(hits[0].filename)))
        print(f"  lib/{os.path.basename(hits[0].filename)} from {os.path.basename(whl)}")
PY

# libtorch.so in the wheel is a shim whose DT_NEEDED pulls in libtorch_cuda.so
# (470 MB plus cuDNN/cuBLAS/...). Drop that entry so the CPU-only tree loads.
# Equivalent to `patchelf --remove-needed libtorch_cuda.so`, without needing patchelf.
python3 - "$TMP/lib/libtorch.so" libtorch_cuda.so <<'PY'
import struct, sys

path, drop = sys.argv[1], set(sys.argv[2:])
data = bytearray(open(path, "rb").read())
if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
    sys.exit(f"{path}: not a little-endian ELF64 file")
phoff, = struct.unpack_from("<Q", data, 0x20)
phentsize, phnum = struct.unpack_from("<HH", data, 0x36)
phdrs = [struct.unpack_from("<IIQQQQQQ", data, phoff + i * phentsize) for i in range(phnum)]
# (p_type, p_flags, p_offset, p_vaddr, p_paddr, p_filesz, p_memsz, p_align)
dyn = next(p for p in phdrs if p[0] == 2)          # PT_DYNAMIC

def vaddr_to_offset(v):
    for p in phdrs:
        if p[0] == 1 and p[3] <= v < p[3] + p[5]:   # PT_LOAD
            return v - p[3] + p[2]
    sys.exit(f"vaddr {v:#x} not in a PT_LOAD segment")

entries, off = [], dyn[2]
while True:
    tag, val = struct.unpack_from("<qQ", data, off)
    entries.append((tag, val))
    off += 16
    if tag == 0:                                    # DT_NULL
        break
strtab = vaddr_to_offset(next(v for t, v in entries if t == 5))  # DT_STRTAB

def string(o):
    end = data.index(0, strtab + o)
    return data[strtab + o:end].decode()

keep = [(t, v) for t, v in entries if not (t == 1 and string(v) in drop)]   # DT_NEEDED
removed = len(entries) - len(keep)
off = dyn[2]
for t, v in keep + [(0, 0)] * removed:
    struct.pack_into("<qQ", data, off, t, v)
    off += 16
open(path, "wb").write(data)
print(f"  lib/libtorch.so: removed {removed} DT_NEEDED entr{'y' if removed == 1 else 'ies'} ({', '.join(sorted(drop))})")
PY

cd "$TMP/lib"
needed() { readelf -d "$1" | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p'; }
GOMP_SONAME=$(needed libtorch_cpu.so | grep '^libgomp' | head -n 1 || true)
[[ -n $GOMP_SONAME ]] || die "libtorch_cpu.so does not list libgomp as NEEDED?"
mv gomp-from-wheel "$GOMP_SONAME"
ln -sfn "$GOMP_SONAME" libgomp.so   # torch-sys links with -lgomp
say "lib/$GOMP_SONAME (+ libgomp.so symlink for -lgomp)"

# Every NEEDED of our libraries must be in lib/ or be a system library.
for f in libtorch_cpu.so libc10.so libtorch.so; do
  if needed "$f" | grep -qx 'libtorch_cuda.so'; then die "$f still needs libtorch_cuda.so"; fi
  missing=$(ldd "$TMP/lib/$f" | grep 'not found' || true)
  [[ -z $missing ]] || die "ldd $f: unresolved libraries:
$missing"
done
# ...and resolve to the copies in lib/ (their RPATH has $ORIGIN), not elsewhere.
LDD_CPU=$(ldd "$TMP/lib/libtorch_cpu.so" | sed 's#/\./#/#g')
for so in libc10.so "$GOMP_SONAME" libcudart.so.13 libcupti.so.13; do
  [[ $LDD_CPU == *"$so => $TMP/lib/$so "* ]] \
    || die "ldd libtorch_cpu.so does not resolve $so inside lib/:
$LDD_CPU"
done
say "ldd: libtorch_cpu.so, libc10.so, libtorch.so resolve every library"
cd "$REPO"

echo "$RECIPE" >"$TMP/.bcal-stamp"
if [[ -e $DEST ]]; then
  [[ $DEST == */libtorch-$TORCH_VERSION ]] || die "refusing to remove $DEST"
  say "removing stale $DEST"
  rm -rf "$DEST"
fi
mv "$TMP" "$DEST"
trap - EXIT
chmod 755 "$DEST"
say "assembled $DEST ($(du -sh "$DEST" | cut -f1))"
link_repo
