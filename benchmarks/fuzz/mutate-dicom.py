#!/usr/bin/env python3
"""Runs itkDynamicMeshRegistration on a DICOM series (the slices in SERIES_DIR, e.g. 8 consecutive slices of
../shared/data/thorax-ct-dicom copied into a folder) of which one slice's header has 1-4 bit flips, overwritten,
inserted or deleted bytes, or a 4-byte field set to 0xFFFFFFFF or 0 (1 iteration, regular mesh, CPU). Prints every
run that ends with anything but exit 0 or 2 (a crash, a hang: 60 s), keeping the series, and a summary.
Usage: mutate-dicom.py TOOL SERIES_DIR OUT_DIR SEED RUNS  (docs/benchmarks.md, 21st session)"""
import os, random, shutil, subprocess, sys
tool, base, OUT = sys.argv[1], sys.argv[2], sys.argv[3]; seed=int(sys.argv[4]); N=int(sys.argv[5]); random.seed(seed)
files=sorted(os.listdir(base)); os.makedirs(OUT, exist_ok=True)
res={}
for t in range(N):
    d=os.path.join(OUT,f'm{seed}'); shutil.rmtree(d,ignore_errors=True); shutil.copytree(base,d)
    f=os.path.join(d,random.choice(files)); b=bytearray(open(f,'rb').read())
    # header ends where pixel data starts
    hdr=b.find(b'\xe0\x7f\x10\x00'); hdr = hdr if hdr>0 else 2000
    kind=random.choice(['flip','overwrite','insert','delete','len'])
    pos=random.randrange(128, hdr+12)
    if kind=='flip':
        for _ in range(random.randint(1,4)):
            p=random.randrange(128,hdr+12); b[p]^=1<<random.randrange(8)
    elif kind=='overwrite':
        n=random.randint(1,16); b[pos:pos+n]=os.urandom(n)
    elif kind=='insert':
        b[pos:pos]=os.urandom(random.randint(1,9))
    elif kind=='delete':
        del b[pos:pos+random.randint(1,9)]
    else:
        # set a 2- or 4-byte length-looking field to a big value
        b[pos:pos+4]=random.choice([b'\xff\xff\xff\xff',b'\x00\x00\x00\x80',b'\xfe\xff\xff\x7f',b'\x00\x00\x00\x00'])
    open(f,'wb').write(b)
    try:
        p=subprocess.run([tool,'--fixed',d,'--moving',base,'--output-dir',os.path.join(OUT,f'o{seed}'),'--iterations','1','--mesh','regular','--backend','cpu'],capture_output=True,timeout=60)
        rc=p.returncode; err=p.stderr.decode(errors='replace').strip().splitlines()
    except subprocess.TimeoutExpired:
        rc='timeout'; err=['']
    key=rc
    res[key]=res.get(key,0)+1
    if rc not in (0,2):
        keep=os.path.join(OUT,f'bad{seed}_{t}'); shutil.copytree(d,keep)
        print(t,kind,pos,rc,(err[-1] if err else '')[:300],flush=True)
print(res,flush=True)
