"""Volume of an organ lattice's leaf tets by where their centroids lie, against the mesh volumes.

Usage: python3 hull_volumes.py CELL LATTICE.vtu MESH_DIR
  LATTICE.vtu: the first frame of `cosurg run --cell CELL --headless --seconds 0.004 --dt 0.004
  --no-tools --out DIR` (DIR/lattice_00000.vtu); MESH_DIR: scenes/meshes/bodies.
A tet whose centroid lies inside a body's mesh counts for that body; one whose centroid lies
outside every mesh ("outside:") counts for the body with the nearest mesh vertex. The engine
gives such a tet the first body's material (the liver's: `MaterialMap::material_at`).
Pure Python (no numpy): ray-cast point-in-mesh tests, a minute or so per lattice.
"""
import base64, struct, re, sys, math
def arrays(path):
    s = open(path).read()
    out = {}
    for m in re.finditer(r'<DataArray type="(\w+)"(?: Name="(\w+)")?[^>]*format="binary"[^>]*>\s*([A-Za-z0-9+/=]+)\s*</DataArray>', s):
        t, name, b = m.group(1), m.group(2) or 'Points', m.group(3)
        raw = base64.b64decode(b)
        n = struct.unpack('<Q', raw[:8])[0]; data = raw[8:8+n]
        fmt = {'Float64':'d','Float32':'f','Int64':'q','UInt64':'Q','Int32':'i','UInt32':'I','UInt8':'B','Int8':'b'}[t]
        out[name] = struct.unpack('<%d%s' % (n // struct.calcsize(fmt), fmt), data)
    return out
def obj(path):
    V, F = [], []
    for l in open(path):
        p = l.split()
        if not p: continue
        if p[0] == 'v': V.append(tuple(map(float, p[1:4])))
        elif p[0] == 'f': F.append(tuple(int(x.split('/')[0]) - 1 for x in p[1:4]))
    return V, F
def sub(a,b): return (a[0]-b[0],a[1]-b[1],a[2]-b[2])
def cross(a,b): return (a[1]*b[2]-a[2]*b[1],a[2]*b[0]-a[0]*b[2],a[0]*b[1]-a[1]*b[0])
def dot(a,b): return a[0]*b[0]+a[1]*b[1]+a[2]*b[2]
def mesh_volume(V,F): return sum(dot(V[a],cross(V[b],V[c])) for a,b,c in F)/6
def inside(p, V, F, d=(0.5773, 0.5774, 0.5771)):
    n = 0
    for a,b,c in F:
        e1, e2 = sub(V[b],V[a]), sub(V[c],V[a]); h = cross(d,e2); det = dot(e1,h)
        if abs(det) < 1e-15: continue
        f = 1/det; s = sub(p,V[a]); u = f*dot(s,h)
        if u < 0 or u > 1: continue
        q = cross(s,e1); v = f*dot(d,q)
        if v < 0 or u+v > 1: continue
        if f*dot(e2,q) > 0: n += 1
    return n % 2 == 1
def mindist(p, V): return min(math.dist(p, v) for v in V)
cell, vtu, meshes = sys.argv[1], sys.argv[2], sys.argv[3]
A = arrays(vtu)
P = [A['Points'][3*i:3*i+3] for i in range(len(A['Points'])//3)]
con, off = A['connectivity'], A['offsets']
bodies = {}
for name in ['liver','gallbladder','cystic_duct','cystic_artery']:
    bodies[name] = obj('%s/%s.obj' % (meshes, name))
vol = {k: 0.0 for k in list(bodies) + ['outside:' + k for k in bodies]}
start = 0
for o in off:
    t = [P[i] for i in con[start:o]]; start = o
    v = abs(dot(sub(t[1],t[0]), cross(sub(t[2],t[0]), sub(t[3],t[0])))) / 6
    c = tuple(sum(x[k] for x in t)/4 for k in range(3))
    hit = next((k for k,(V,F) in bodies.items() if inside(c, V, F)), None)
    if hit is None:
        near = min(bodies, key=lambda k: mindist(c, bodies[k][0]))
        vol['outside:' + near] += v
    else:
        vol[hit] += v
print(f"cell {cell}: mesh volumes (cm3): " + ", ".join(f"{k} {mesh_volume(*bodies[k])*1e6:.1f}" for k in bodies))
print(f"cell {cell}: lattice volume by tet centroid (cm3): " + ", ".join(f"{k} {vol[k]*1e6:.1f}" for k in vol))
