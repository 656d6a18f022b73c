#!/usr/bin/env python3
# Pairs of shapes that are not in the tests (see README.md): writes DIR/<case>/{fixed,moving}.mha (float MetaImage).
# Standard library only. Usage: make-shapes.py DIR
import math, struct, os, sys
def write_mha(path, w, h, data, spacing=(1.0,1.0), origin=(0.0,0.0)):
    with open(path,'wb') as f:
        hdr = ("ObjectType = Image\nNDims = 2\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
               f"DimSize = {w} {h}\nElementSpacing = {spacing[0]} {spacing[1]}\nOffset = {origin[0]} {origin[1]}\n"
               "ElementType = MET_FLOAT\nElementDataFile = LOCAL\n")
        f.write(hdr.encode()); f.write(struct.pack('<%df'%len(data), *data))
def shape(w,h,inside,aa=3):
    out=[]
    for y in range(h):
        for x in range(w):
            c=0
            for sy in range(aa):
                for sx in range(aa):
                    if inside(x+(sx+0.5)/aa-0.5, y+(sy+0.5)/aa-0.5): c+=1
            out.append(255.0*c/(aa*aa))
    return out
cases={}
W=H=256; cx=cy=128
circle=lambda r:(lambda x,y:(x-cx)**2+(y-cy)**2<=r*r)
def star(x,y):
    dx,dy=x-cx,y-cy; r=math.hypot(dx,dy); t=math.atan2(dy,dx)
    return r <= 60+25*math.cos(5*t)
def cshape(x,y):
    dx,dy=x-cx,y-cy; r=math.hypot(dx,dy); t=math.atan2(dy,dx)
    return 45<=r<=85 and abs(t)>0.6
def square(x,y): return abs(x-cx)<=60 and abs(y-cy)<=60
def ellipse(x,y): return ((x-cx-15)/80)**2+((y-cy+10)/45)**2<=1
if len(sys.argv) != 2:
    sys.exit("usage: make-shapes.py DIR")
d=sys.argv[1]
os.makedirs(d,exist_ok=True)
for name,(src,dst) in {"star":(circle(70),star),"cshape":(square,cshape),"ellipse":(circle(60),ellipse)}.items():
    os.makedirs(f"{d}/{name}",exist_ok=True)
    write_mha(f"{d}/{name}/moving.mha",W,H,shape(W,H,src))
    write_mha(f"{d}/{name}/fixed.mha",W,H,shape(W,H,dst))
# anisotropic, non-square: 300x200 with spacing (1, 1.5): physical circle -> ellipse
def phys(sx,sy,f): return lambda x,y:f(x*sx,y*sy)
Wa,Ha=300,200
ca=lambda x,y:(x-150)**2+(y-150)**2<=55**2
ea=lambda x,y:((x-160)/85)**2+((y-150)/50)**2<=1
os.makedirs(f"{d}/aniso",exist_ok=True)
write_mha(f"{d}/aniso/moving.mha",Wa,Ha,shape(Wa,Ha,phys(1,1.5,ca)),spacing=(1.0,1.5),origin=(-20,7))
write_mha(f"{d}/aniso/fixed.mha",Wa,Ha,shape(Wa,Ha,phys(1,1.5,ea)),spacing=(1.0,1.5),origin=(-20,7))
# smooth grey blobs with a known smooth warp
def blobs(x,y):
    v=0
    for (bx,by,s,a) in [(80,90,25,200),(170,100,30,150),(120,180,20,255),(190,190,15,120)]:
        v+=a*math.exp(-((x-bx)**2+(y-by)**2)/(2*s*s))
    return v
def warp(x,y): return (x+6*math.sin(2*math.pi*y/256), y+5*math.sin(2*math.pi*x/200))
os.makedirs(f"{d}/blobs",exist_ok=True)
write_mha(f"{d}/blobs/fixed.mha",W,H,[blobs(x,y) for y in range(H) for x in range(W)])
write_mha(f"{d}/blobs/moving.mha",W,H,[blobs(*warp(x,y)) for y in range(H) for x in range(W)])
# 3D: a sphere (moving) to an ellipsoid (fixed), 48 x 44 x 40 voxels of 1 x 1 x 1.2 mm, 4 samples per voxel
def write_mha3(path, n, data, sp, origin=(0,0,0), direction=(1,0,0,0,1,0,0,0,1)):
    with open(path,'wb') as f:
        f.write(("ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
                 "DimSize = %d %d %d\nElementSpacing = %g %g %g\nOffset = %g %g %g\nTransformMatrix = %s\n"
                 "ElementType = MET_FLOAT\nElementDataFile = LOCAL\n"
                 % (n[0], n[1], n[2], sp[0], sp[1], sp[2], origin[0], origin[1], origin[2],
                    " ".join("%.17g" % v for v in direction))).encode())
        f.write(struct.pack('<%df' % len(data), *data))
N3=(48,44,40); sp3=(1.0,1.0,1.2)
def volume(ins, n=N3, sp=sp3):
    out=[]
    for z in range(n[2]):
        for y in range(n[1]):
            for x in range(n[0]):
                c=0
                for s in ((0.25,0.25,0.25),(0.75,0.25,0.75),(0.25,0.75,0.75),(0.75,0.75,0.25)):
                    if ins((x+s[0]-0.5)*sp[0],(y+s[1]-0.5)*sp[1],(z+s[2]-0.5)*sp[2]): c+=1
                out.append(100.0*c/4)
    return out
os.makedirs(f"{d}/sphere3d",exist_ok=True)
write_mha3(f"{d}/sphere3d/moving.mha",N3,volume(lambda x,y,z:(x-24)**2+(y-22)**2+(z-24)**2<=12**2),sp3)
write_mha3(f"{d}/sphere3d/fixed.mha",N3,volume(lambda x,y,z:((x-25)/16)**2+((y-21)/10)**2+((z-24)/13)**2<=1),sp3)
# 3D circle-to-leaf: 96 x 48 x 48 voxels of 1 mm; a sphere of radius 12 at (64, 24, 24) (moving) to the same hemisphere
# for x >= 64 and a half-ellipsoid of semi-axes 48 x 12 x 12 towards -x (fixed): the sphere must stretch fourfold
NL=(96,48,48); spL=(1.0,1.0,1.0)
def leaf3d(x,y,z):
    if x>=64: return (x-64)**2+(y-24)**2+(z-24)**2<=144
    return ((x-64)/48)**2+((y-24)/12)**2+((z-24)/12)**2<=1
os.makedirs(f"{d}/leaf3d",exist_ok=True)
write_mha3(f"{d}/leaf3d/moving.mha",NL,volume(lambda x,y,z:(x-64)**2+(y-24)**2+(z-24)**2<=144,NL,spL),spL)
write_mha3(f"{d}/leaf3d/fixed.mha",NL,volume(leaf3d,NL,spL),spL)
# 30th session: motions the pairs above do not have (a rotation, two objects moving apart, a strong compression, a
# neck, a small image) and a 3D pair on an oblique grid
def rotsquare(t):
    c, sn = math.cos(t), math.sin(t)
    return lambda x,y: abs((x-cx)*c+(y-cy)*sn)<=50 and abs(-(x-cx)*sn+(y-cy)*c)<=50
def disks(*cs): return lambda x,y: any((x-a)**2+(y-b)**2<=r*r for (a,b,r) in cs)
def dumbbell(x,y):
    return (x-cx+55)**2+(y-cy)**2<=40**2 or (x-cx-55)**2+(y-cy)**2<=40**2 or (abs(x-cx)<=55 and abs(y-cy)<=12)
for name,(src,dst) in {"rotsquare":(rotsquare(0.0),rotsquare(math.radians(30))),
                       "twodisks":(disks((80,128,35),(176,128,35)),disks((70,110,35),(186,150,35))),
                       "shrink":(circle(90),circle(50)),
                       "dumbbell":(circle(70),dumbbell)}.items():
    os.makedirs(f"{d}/{name}",exist_ok=True)
    write_mha(f"{d}/{name}/moving.mha",W,H,shape(W,H,src))
    write_mha(f"{d}/{name}/fixed.mha",W,H,shape(W,H,dst))
def smallellipse(x,y):
    c, sn = math.cos(0.3), math.sin(0.3)
    u, v = (x-32)*c+(y-32)*sn, -(x-32)*sn+(y-32)*c
    return (u/22)**2+(v/10)**2<=1
os.makedirs(f"{d}/small",exist_ok=True)
write_mha(f"{d}/small/moving.mha",64,64,shape(64,64,lambda x,y:(x-32)**2+(y-32)**2<=15**2))
write_mha(f"{d}/small/fixed.mha",64,64,shape(64,64,smallellipse))
# 3D on an oblique grid: 80 x 70 x 30 voxels of 0.8 x 0.9 x 2.5 mm, rotated by 30 degrees about z; a sphere of radius
# 18 mm to an ellipsoid 24 x 14 x 22 mm moved by 4 mm (positions in the grid frame, mm)
NO=(80,70,30); spO=(0.8,0.9,2.5); c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
os.makedirs(f"{d}/oblique3d",exist_ok=True)
for name, ins in (("moving", lambda x,y,z:(x-32)**2+(y-31)**2+(z-37)**2<=18**2),
                  ("fixed", lambda x,y,z:((x-36)/24)**2+((y-31)/14)**2+((z-37)/22)**2<=1)):
    write_mha3(f"{d}/oblique3d/{name}.mha",NO,volume(ins,NO,spO),spO,(-20,10,5),(c30,s30,0,-s30,c30,0,0,0,1))
