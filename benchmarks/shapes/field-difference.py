#!/usr/bin/env python3
# Largest difference between two displacement.nii.gz files of the tool (mm), and the share of components above 0.05.
# Standard library only. Usage: field-difference.py A B
import gzip, struct, sys
def rd(p):
    d = gzip.open(p).read()
    off = int(struct.unpack('<f', d[108:112])[0])
    dims = struct.unpack('<8h', d[40:56])
    return d[off:], dims
a, da = rd(sys.argv[1]); b, db = rd(sys.argv[2])
n = len(a) // 4
fa = struct.unpack('<%df' % n, a); fb = struct.unpack('<%df' % n, b)
m = max(abs(x - y) for x, y in zip(fa, fb)); ma = max(abs(x) for x in fa)
bad = sum(1 for x, y in zip(fa, fb) if abs(x - y) > 0.05)
print('dims', da[:6], 'max |u|', ma, 'max diff', m, 'components > 0.05:', bad, 'of', n)
