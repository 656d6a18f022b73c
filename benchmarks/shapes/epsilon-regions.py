#!/usr/bin/env python3
"""Where a registration of circle-to-epsilon is still wrong (Python standard library only; float32 NIfTI-1 images,
.nii or .nii.gz, as dmrGenerateShapes and itkDynamicMeshRegistration write them):

  epsilon-regions.py FIXED MOVING WARPED [WARPED ...]

For each warped image: the pixels that must be emptied (inside the source, outside the target: the bays and their
entrances) and are still inside (warped >= 0.5); the pixels that must be filled (inside the target, outside the
source disk of radius 120) and are still outside, in total, by 30-degree sector around the image centre (counted
from +x towards +y) and by 5-pixel ring from radius 120. docs/benchmarks.md (29th session) uses it."""
import gzip
import math
import struct
import sys


def read(path):
    opener = gzip.open if path.endswith('.gz') else open
    with opener(path, 'rb') as f:
        b = f.read()
    dims = struct.unpack_from('<8h', b, 40)
    datatype = struct.unpack_from('<h', b, 70)[0]
    offset = int(struct.unpack_from('<f', b, 108)[0])
    if dims[0] != 2 or datatype != 16:
        sys.exit(f'{path}: not a 2D float32 NIfTI image')
    n = dims[1] * dims[2]
    return dims[1], dims[2], struct.unpack_from(f'<{n}f', b, offset)


def main():
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    width, height, fixed = read(sys.argv[1])
    _, _, moving = read(sys.argv[2])
    cx, cy = (width - 1) / 2, (height - 1) / 2
    empty = [i for i in range(width * height) if fixed[i] < 0.5 <= moving[i]]
    fill = [i for i in range(width * height) if moving[i] < 0.5 <= fixed[i]]
    for path in sys.argv[3:]:
        w, h, warped = read(path)
        if (w, h) != (width, height):
            sys.exit(f'{path}: not on the fixed grid')
        inside = sum(1 for i in empty if warped[i] >= 0.5)
        outside = [i for i in fill if warped[i] < 0.5]
        sectors, rings = [0] * 12, [0] * 6
        for i in outside:
            x, y = i % width - cx, i // width - cy
            sectors[int((math.degrees(math.atan2(y, x)) + 360) % 360 // 30)] += 1
            rings[min(5, max(0, int((math.hypot(x, y) - 120) // 5)))] += 1
        print(f'{path}: to empty {len(empty)} px, still inside {inside} ({100 * inside / len(empty):.1f} %); '
              f'to fill {len(fill)} px, still outside {len(outside)} ({100 * len(outside) / len(fill):.1f} %); '
              f'outside by 30-degree sector {sectors}, by ring from radius 120 {rings}')


if __name__ == '__main__':
    main()
