#!/usr/bin/env python3
# Pairs larger than the tests' (2048 x 1536 2D, a thin 64 x 48 x 5 volume, a 96^3 sphere to ellipsoid, a 6 x 5 image) as float
# MetaImage files in DIR, for comparing the GPU and CPU back-ends. Standard library only. Usage: make-large-pairs.py DIR
import struct, os, math, sys
def w(p, n, data, sp):
    nd = len(n)
    with open(p, 'wb') as f:
        f.write(("ObjectType = Image\nNDims = %d\nBinaryData = True\nBinaryDataByteOrderMSB = False\nDimSize = %s\nElementSpacing = %s\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n" % (nd, ' '.join(map(str, n)), ' '.join(map(str, sp)))).encode())
        f.write(struct.pack('<%df' % len(data), *data))
d = sys.argv[1]
os.makedirs(d, exist_ok=True)
# big non-square 2D: 2048 x 1536, disk -> ellipse (no anti-aliasing)
W, H = 2048, 1536
def img2(f):
    return [100.0 if f(x, y) else 0.0 for y in range(H) for x in range(W)]
w(d + '/big_m.mha', (W, H), img2(lambda x, y: (x - 1000) ** 2 + (y - 760) ** 2 <= 400 ** 2), (0.5, 0.5))
w(d + '/big_f.mha', (W, H), img2(lambda x, y: ((x - 1030) / 520.0) ** 2 + ((y - 750) / 330.0) ** 2 <= 1), (0.5, 0.5))
# thin 3D: 64 x 48 x 5 smooth blobs
N = (64, 48, 5)
def img3(cx):
    return [100.0 * math.exp(-((x - cx) ** 2 + (y - 24) ** 2) / 200.0 - (z - 2) ** 2 / 8.0) for z in range(N[2]) for y in range(N[1]) for x in range(N[0])]
w(d + '/thin_m.mha', N, img3(30), (1, 1, 3))
w(d + '/thin_f.mha', N, img3(34), (1, 1, 3))
# tiny 2D: 6 x 5
w(d + '/tiny_m.mha', (6, 5), [float((x * 3 + y * 7) % 11) for y in range(5) for x in range(6)], (1, 1))
w(d + '/tiny_f.mha', (6, 5), [float((x * 3 + y * 7 + 2) % 11) for y in range(5) for x in range(6)], (1, 1))
# many nodes 3D: 96^3 sphere -> ellipsoid
M = 96
def img4(f):
    return [100.0 if f(x, y, z) else 0.0 for z in range(M) for y in range(M) for x in range(M)]
w(d + '/many_m.mha', (M, M, M), img4(lambda x, y, z: (x - 48) ** 2 + (y - 48) ** 2 + (z - 48) ** 2 <= 25 ** 2), (1, 1, 1))
w(d + '/many_f.mha', (M, M, M), img4(lambda x, y, z: ((x - 50) / 32.0) ** 2 + ((y - 47) / 22.0) ** 2 + ((z - 48) / 26.0) ** 2 <= 1), (1, 1, 1))
