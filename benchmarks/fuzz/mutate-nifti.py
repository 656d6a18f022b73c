#!/usr/bin/env python3
"""Runs itkDynamicMeshRegistration on NIfTI-1 files (64 x 64 float disks) whose header has 1-3 fields set to extreme
values (0, -1, 1e30, NaN, inf, 2^31, ...) or random bytes, as fixed or moving image (1 iteration, regular mesh, CPU).
Prints every run that ends with anything but exit 0 or 2 (a crash, a hang: 60 s), keeping its file, and a summary.
Usage: mutate-nifti.py TOOL OUT_DIR SEED RUNS  (docs/benchmarks.md, 21st session)"""
import os, random, struct, subprocess, sys, math, shutil
TOOL, OUT = sys.argv[1], sys.argv[2]; seed=int(sys.argv[3]); N=int(sys.argv[4]); random.seed(seed)
W=64
def nifti(shift):
    h=bytearray(348)
    struct.pack_into('<i',h,0,348)
    struct.pack_into('<8h',h,40,2,W,W,1,1,1,1,1)
    struct.pack_into('<hh',h,70,16,32)
    struct.pack_into('<8f',h,76,1,1,1,1,1,1,1,1)
    struct.pack_into('<f',h,108,352.0)
    struct.pack_into('<f',h,112,1.0)
    struct.pack_into('<h',h,252,1); struct.pack_into('<h',h,254,1)
    struct.pack_into('<4f',h,280,1,0,0,0); struct.pack_into('<4f',h,296,0,1,0,0); struct.pack_into('<4f',h,312,0,0,1,0)
    h[344:348]=b'n+1\0'
    data=b''.join(struct.pack('<f',100.0 if (x-32-shift)**2+(y-32)**2<15**2 else 0.0) for y in range(W) for x in range(W))
    return bytes(h)+b'\0\0\0\0'+data
base=bytearray(nifti(0)); good=nifti(3)
d=os.path.join(OUT,f'nifti{seed}'); os.makedirs(d,exist_ok=True)
open(f'{d}/good.nii','wb').write(good)
fields=[(0,'i'),(40,'h'),(42,'h'),(44,'h'),(46,'h'),(48,'h'),(70,'h'),(72,'h'),(76,'f'),(80,'f'),(84,'f'),(88,'f'),(108,'f'),(112,'f'),(116,'f'),(252,'h'),(254,'h'),(256,'f'),(260,'f'),(264,'f'),(268,'f'),(272,'f'),(276,'f'),(280,'f'),(284,'f'),(296,'f'),(312,'f'),(324,'f'),(344,'i')]
vals={'h':[0,-1,1,2,3,4,5,7,8,16,32,64,128,255,256,512,768,1024,2304,4096,32767,-32768],'i':[0,-1,348,540,1<<30,-(1<<31)],
      'f':[0.0,-1.0,1e-30,1e30,float('nan'),float('inf'),-float('inf'),1e-8,3.0,0.5,1e10,-1e10,2.0**31,1e-40]}
res={}
for t in range(N):
    b=bytearray(base)
    for _ in range(random.randint(1,3)):
        if random.random()<0.7:
            off,ty=random.choice(fields); v=random.choice(vals[ty])
            struct.pack_into('<'+ty,b,off,v)
        else:
            p=random.randrange(0,352); b[p]=random.randrange(256)
    f=f'{d}/m.nii'; open(f,'wb').write(b)
    args=[TOOL,'--fixed',f,'--moving',f'{d}/good.nii','--output-dir',f'{d}/o','--iterations','1','--mesh','regular','--backend','cpu','--nodes','16']
    if random.random()<0.5: args[2],args[4]=args[4],args[2]
    try:
        p=subprocess.run(args,capture_output=True,timeout=60); rc=p.returncode; err=p.stderr.decode(errors='replace').strip().splitlines()
    except subprocess.TimeoutExpired:
        rc='timeout'; err=['']
    res[rc]=res.get(rc,0)+1
    if rc not in (0,2):
        shutil.copy(f,f'{d}/bad_{t}.nii'); print(t,rc,args[2]==f,(err[-1] if err else '')[:300],flush=True)
print(res,flush=True)
