#!/usr/bin/env python3
"""Runs itkDynamicMeshRegistration on MetaImage, NRRD and legacy VTK images and ITK transform files
(--initial-transform, half the runs with --inverse) whose header lines have numbers replaced by NaN, inf, 1e308,
-2147483649, words or lists, lines duplicated or deleted (1 iteration, regular mesh, CPU). Prints every run that ends
with anything but exit 0, or exit 2 with one line on stderr, keeping its file, and a summary.
Usage: mutate-text-headers.py TOOL OUT_DIR SEED RUNS  (docs/benchmarks.md, 21st session)"""
import os, random, struct, subprocess, sys, shutil, re
TOOL, OUT = sys.argv[1], sys.argv[2]; seed=int(sys.argv[3]); N=int(sys.argv[4]); random.seed(seed)
W=32
d=os.path.join(OUT,f'text{seed}'); os.makedirs(d,exist_ok=True)
img=lambda s: b''.join(struct.pack('<f',100.0 if (x-16-s)**2+(y-16)**2<8**2 else 0.0) for y in range(W) for x in range(W))
imgbe=lambda s: b''.join(struct.pack('>f',100.0 if (x-16-s)**2+(y-16)**2<8**2 else 0.0) for y in range(W) for x in range(W))
mha='ObjectType = Image\nNDims = 2\nBinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = False\nTransformMatrix = 1 0 0 1\nOffset = 0 0\nCenterOfRotation = 0 0\nElementSpacing = 1 1\nDimSize = 32 32\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n'
nrrd='NRRD0004\ntype: float\ndimension: 2\nspace: left-posterior\nsizes: 32 32\nspace directions: (1,0) (0,1)\nkinds: domain domain\nendian: little\nencoding: raw\nspace origin: (0,0)\n\n'
vtk='# vtk DataFile Version 3.0\nx\nBINARY\nDATASET STRUCTURED_POINTS\nDIMENSIONS 32 32 1\nSPACING 1 1 1\nORIGIN 0 0 0\nPOINT_DATA 1024\nSCALARS s float 1\nLOOKUP_TABLE default\n'
tfm='#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_2_2\nParameters: 1 0 0 1 0.5 -0.5\nFixedParameters: 16 16\n'
open(f'{d}/good.mha','wb').write(mha.encode()+img(3))
specials=['nan','inf','-inf','0','-1','1e308','-1e308','1e-320','99999999999','-2147483649','4294967296','1e38','abc','','1 2 3 4 5 6 7 8 9','0x10','1,5']
res={}
for t in range(N):
    kind=random.choice(['mha','nrrd','vtk','tfm'])
    text={'mha':mha,'nrrd':nrrd,'vtk':vtk,'tfm':tfm}[kind]
    lines=text.split('\n')
    for _ in range(random.randint(1,3)):
        op=random.random(); i=random.randrange(len(lines))
        if op<0.6:
            toks=list(re.finditer(r'-?[0-9.]+(e-?[0-9]+)?',lines[i]))
            if toks:
                m=random.choice(toks); lines[i]=lines[i][:m.start()]+random.choice(specials)+lines[i][m.end():]
        elif op<0.75: lines.insert(i,lines[i])
        elif op<0.85:
            if lines[i] not in ('',): del lines[i]
        else:
            lines[i]=lines[i]+' '+random.choice(specials)
    text='\n'.join(lines)
    ext={'mha':'mha','nrrd':'nrrd','vtk':'vtk','tfm':'tfm'}[kind]
    f=f'{d}/m.{ext}'
    if kind=='tfm':
        open(f,'w').write(text)
        args=['--fixed',f'{d}/good.mha','--moving',f'{d}/good.mha','--initial-transform',f]
        if random.random()<0.5: args.append('--inverse')
    else:
        open(f,'wb').write(text.encode()+(imgbe(0) if kind=='vtk' else img(0)))
        args=['--fixed',f,'--moving',f'{d}/good.mha'] if random.random()<0.5 else ['--fixed',f'{d}/good.mha','--moving',f]
    try:
        p=subprocess.run([TOOL]+args+['--output-dir',f'{d}/o','--iterations','1','--mesh','regular','--backend','cpu','--nodes','16'],capture_output=True,timeout=60)
        rc=p.returncode; err=p.stderr.decode(errors='replace').strip().splitlines()
    except subprocess.TimeoutExpired:
        rc='timeout'; err=['']
    res[(kind,rc)]=res.get((kind,rc),0)+1
    if rc not in (0,2) or (rc==2 and len(err)!=1):
        shutil.copy(f,f'{d}/bad_{t}.{ext}'); print(t,kind,rc,len(err),(err[-1] if err else '')[:300],flush=True)
print(res,flush=True)
