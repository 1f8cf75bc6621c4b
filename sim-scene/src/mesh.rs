//! Triangle meshes: loading (OBJ, STL, PLY), writing (OBJ) and geometric checks.
//!
//! All formats are read into one indexed representation, [`TriMesh`]. Polygons are
//! fan-triangulated, STL's per-triangle vertices are merged when bit-identical, and
//! positions are widened to `f64`.

use std::collections::HashMap;
use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::Aabb;

/// Errors from reading or writing a mesh file. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The file extension names no supported format.
    #[error("{path}: unsupported mesh format (expected .obj, .stl or .ply)")]
    UnsupportedFormat {
        /// The file.
        path: PathBuf,
    },
    /// The file could not be parsed.
    #[error("{path}: not a valid {format} file: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// "OBJ", "STL" or "PLY".
        format: &'static str,
        /// What the parser reported.
        message: String,
    },
    /// The file parsed but its content is not a usable triangle mesh.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Mesh file formats understood by [`TriMesh::load`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Wavefront OBJ (positions and faces; materials and normals are ignored).
    Obj,
    /// STL, binary or ASCII.
    Stl,
    /// PLY, ASCII or binary (either endianness).
    Ply,
}

impl MeshFormat {
    /// The format named by a file extension (case-insensitive).
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "obj" => Some(Self::Obj),
            "stl" => Some(Self::Stl),
            "ply" => Some(Self::Ply),
            _ => None,
        }
    }
}

/// An indexed triangle mesh in metres.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions.
    pub vertices: Vec<Vector3<f64>>,
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// Reads a mesh file; the format is chosen by the extension (`.obj`, `.stl`, `.ply`).
    /// OBJ vertices are numbered in order of first use by a face (unused ones dropped);
    /// STL vertices are merged when bit-identical; PLY keeps the file order.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, MeshError> {
        let path = path.as_ref();
        let format = MeshFormat::from_path(path).ok_or_else(|| MeshError::UnsupportedFormat {
            path: path.to_path_buf(),
        })?;
        let bytes = std::fs::read(path).map_err(|source| MeshError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes, format, path)
    }

    /// Parses mesh file content. `label` names the file in errors.
    pub fn from_bytes(bytes: &[u8], format: MeshFormat, label: &Path) -> Result<Self, MeshError> {
        let mesh = match format {
            MeshFormat::Obj => parse_obj(bytes, label)?,
            MeshFormat::Stl => parse_stl(bytes, label)?,
            MeshFormat::Ply => parse_ply(bytes, label)?,
        };
        mesh.check_indices(label)?;
        tracing::debug!(
            file = %label.display(),
            vertices = mesh.vertices.len(),
            triangles = mesh.triangles.len(),
            "mesh loaded"
        );
        Ok(mesh)
    }

    fn check_indices(&self, label: &Path) -> Result<(), MeshError> {
        if self.triangles.is_empty() {
            return Err(MeshError::Invalid {
                path: label.to_path_buf(),
                message: "mesh has no triangles".into(),
            });
        }
        let n = self.vertices.len();
        for (i, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&v| v as usize >= n) {
                return Err(MeshError::Invalid {
                    path: label.to_path_buf(),
                    message: format!(
                        "triangle {i} refers to vertex {:?} but there are only {n} vertices",
                        t
                    ),
                });
            }
        }
        if let Some(i) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(MeshError::Invalid {
                path: label.to_path_buf(),
                message: format!("vertex {i} has a non-finite coordinate"),
            });
        }
        Ok(())
    }

    /// Writes the mesh as OBJ with `decimals` digits after the point.
    pub fn write_obj_to<W: Write>(
        &self,
        w: &mut W,
        decimals: usize,
        header: &str,
    ) -> std::io::Result<()> {
        for line in header.lines() {
            writeln!(w, "# {line}")?;
        }
        for v in &self.vertices {
            writeln!(
                w,
                "v {} {} {}",
                fmt_fixed(v.x, decimals),
                fmt_fixed(v.y, decimals),
                fmt_fixed(v.z, decimals)
            )?;
        }
        for t in &self.triangles {
            writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
        }
        Ok(())
    }

    /// Writes the mesh as an OBJ file (9 decimals, i.e. nanometres).
    pub fn write_obj(&self, path: impl AsRef<Path>) -> Result<(), MeshError> {
        let path = path.as_ref();
        let io = |source| MeshError::Io {
            path: path.to_path_buf(),
            source,
        };
        let file = std::fs::File::create(path).map_err(io)?;
        let mut w = std::io::BufWriter::new(file);
        self.write_obj_to(&mut w, 9, "").map_err(io)?;
        w.flush().map_err(io)
    }

    /// Axis-aligned bounding box of the vertices (`None` for an empty mesh).
    pub fn bounding_box(&self) -> Option<Aabb> {
        Aabb::from_points(self.vertices.iter())
    }

    /// Signed enclosed volume in m³ (positive when closed and outward-oriented).
    pub fn signed_volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = self.corners(t);
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum()
    }

    /// Total surface area in m².
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = self.corners(t);
                0.5 * (b - a).cross(&(c - a)).norm()
            })
            .sum()
    }

    fn corners(&self, t: &[u32; 3]) -> [Vector3<f64>; 3] {
        [
            self.vertices[t[0] as usize],
            self.vertices[t[1] as usize],
            self.vertices[t[2] as usize],
        ]
    }

    /// Undirected edge → number of triangles using it.
    fn edge_counts(&self) -> HashMap<(u32, u32), (u32, u32)> {
        // value: (uses as a->b with a<b, uses as b->a)
        let mut m: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if a < b {
                    m.entry((a, b)).or_default().0 += 1;
                } else {
                    m.entry((b, a)).or_default().1 += 1;
                }
            }
        }
        m
    }

    /// Number of edges not shared by exactly two triangles.
    pub fn non_manifold_or_boundary_edges(&self) -> usize {
        self.edge_counts()
            .values()
            .filter(|(f, r)| f + r != 2)
            .count()
    }

    /// True when every edge is shared by exactly two triangles (watertight, manifold edges).
    pub fn is_closed(&self) -> bool {
        !self.triangles.is_empty() && self.non_manifold_or_boundary_edges() == 0
    }

    /// True when every edge is used once in each direction, i.e. neighbouring triangles
    /// agree on their orientation. Implies [`is_closed`](Self::is_closed).
    pub fn is_consistently_oriented(&self) -> bool {
        !self.triangles.is_empty() && self.edge_counts().values().all(|&(f, r)| f == 1 && r == 1)
    }

    /// Closed, consistently oriented and enclosing a positive volume: normals point out.
    pub fn is_outward_oriented(&self) -> bool {
        self.is_consistently_oriented() && self.signed_volume() > 0.0
    }

    /// The same mesh with vertices numbered in order of first use by the triangles and
    /// unused vertices dropped. OBJ files are read this way (tobj), so a mesh in this order
    /// survives an OBJ write/read round trip with identical numbering.
    pub fn renumbered_by_first_use(&self) -> TriMesh {
        let mut map = vec![u32::MAX; self.vertices.len()];
        let mut out = TriMesh::default();
        for t in &self.triangles {
            let mut nt = [0u32; 3];
            for k in 0..3 {
                let v = t[k] as usize;
                if map[v] == u32::MAX {
                    map[v] = out.vertices.len() as u32;
                    out.vertices.push(self.vertices[v]);
                }
                nt[k] = map[v];
            }
            out.triangles.push(nt);
        }
        out
    }

    /// Reverses every triangle (flips all normals).
    pub fn flip(&mut self) {
        for t in &mut self.triangles {
            t.swap(1, 2);
        }
    }

    /// Generalised winding number of `p` (≈1 inside a closed outward mesh, ≈0 outside).
    pub fn winding_number(&self, p: &Vector3<f64>) -> f64 {
        let mut sum = 0.0;
        for t in &self.triangles {
            let [a, b, c] = self.corners(t);
            let (a, b, c) = (a - p, b - p, c - p);
            let (la, lb, lc) = (a.norm(), b.norm(), c.norm());
            let num = a.dot(&b.cross(&c));
            let den = la * lb * lc + a.dot(&b) * lc + b.dot(&c) * la + c.dot(&a) * lb;
            sum += 2.0 * num.atan2(den);
        }
        sum / (4.0 * std::f64::consts::PI)
    }

    /// True when `p` is inside the (closed) mesh, by winding number.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        self.winding_number(p) > 0.5
    }

    /// Area-weighted vertex normals (unit length; zero for isolated vertices).
    pub fn vertex_normals(&self) -> Vec<Vector3<f64>> {
        let mut n = vec![Vector3::zeros(); self.vertices.len()];
        for t in &self.triangles {
            let [a, b, c] = self.corners(t);
            let fnorm = (b - a).cross(&(c - a));
            for &v in t {
                n[v as usize] += fnorm;
            }
        }
        for v in &mut n {
            let l = v.norm();
            if l > 0.0 {
                *v /= l;
            }
        }
        n
    }
}

/// Formats `x` with exactly `decimals` digits, never printing `-0.000`.
pub(crate) fn fmt_fixed(x: f64, decimals: usize) -> String {
    let s = format!("{x:.decimals$}");
    if s.starts_with('-') && s[1..].bytes().all(|c| c == b'0' || c == b'.') {
        s[1..].to_string()
    } else {
        s
    }
}

fn parse_obj(bytes: &[u8], label: &Path) -> Result<TriMesh, MeshError> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    let mut reader = Cursor::new(bytes);
    let (models, _materials) =
        tobj::load_obj_buf(&mut reader, &opts, |_| Err(tobj::LoadError::OpenFileFailed)).map_err(
            |e| MeshError::Parse {
                path: label.to_path_buf(),
                format: "OBJ",
                message: e.to_string(),
            },
        )?;
    let mut mesh = TriMesh::default();
    for m in models {
        let base = mesh.vertices.len() as u32;
        mesh.vertices.extend(
            m.mesh
                .positions
                .chunks_exact(3)
                .map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)),
        );
        mesh.triangles.extend(
            m.mesh
                .indices
                .chunks_exact(3)
                .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
        );
    }
    Ok(mesh)
}

fn parse_stl(bytes: &[u8], label: &Path) -> Result<TriMesh, MeshError> {
    let mut cursor = Cursor::new(bytes);
    let indexed = stl_io::read_stl(&mut cursor).map_err(|e| MeshError::Parse {
        path: label.to_path_buf(),
        format: "STL",
        message: e.to_string(),
    })?;
    Ok(TriMesh {
        vertices: indexed
            .vertices
            .iter()
            .map(|v| Vector3::new(v.0[0] as f64, v.0[1] as f64, v.0[2] as f64))
            .collect(),
        triangles: indexed
            .faces
            .iter()
            .map(|f| {
                [
                    f.vertices[0] as u32,
                    f.vertices[1] as u32,
                    f.vertices[2] as u32,
                ]
            })
            .collect(),
    })
}

fn parse_ply(bytes: &[u8], label: &Path) -> Result<TriMesh, MeshError> {
    use ply_rs::parser::Parser;
    use ply_rs::ply::{DefaultElement, Property};
    let perr = |message: String| MeshError::Parse {
        path: label.to_path_buf(),
        format: "PLY",
        message,
    };
    let mut reader = Cursor::new(bytes);
    let parser = Parser::<DefaultElement>::new();
    let ply = parser
        .read_ply(&mut reader)
        .map_err(|e| perr(e.to_string()))?;
    let scalar = |p: &Property| -> Option<f64> {
        Some(match *p {
            Property::Char(v) => v as f64,
            Property::UChar(v) => v as f64,
            Property::Short(v) => v as f64,
            Property::UShort(v) => v as f64,
            Property::Int(v) => v as f64,
            Property::UInt(v) => v as f64,
            Property::Float(v) => v as f64,
            Property::Double(v) => v,
            _ => return None,
        })
    };
    let list = |p: &Property| -> Option<Vec<i64>> {
        Some(match p {
            Property::ListChar(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUChar(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListInt(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUInt(v) => v.iter().map(|&x| x as i64).collect(),
            _ => return None,
        })
    };
    let verts = ply
        .payload
        .get("vertex")
        .ok_or_else(|| perr("no `vertex` element".into()))?;
    let mut mesh = TriMesh::default();
    for (i, v) in verts.iter().enumerate() {
        let mut c = [0.0; 3];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            c[k] = v
                .get(*name)
                .and_then(scalar)
                .ok_or_else(|| perr(format!("vertex {i} has no numeric `{name}`")))?;
        }
        mesh.vertices.push(Vector3::new(c[0], c[1], c[2]));
    }
    let faces = ply
        .payload
        .get("face")
        .ok_or_else(|| perr("no `face` element".into()))?;
    for (i, f) in faces.iter().enumerate() {
        let idx = f
            .get("vertex_indices")
            .or_else(|| f.get("vertex_index"))
            .and_then(list)
            .ok_or_else(|| perr(format!("face {i} has no `vertex_indices` list")))?;
        if idx.len() < 3 {
            return Err(perr(format!("face {i} has {} vertices", idx.len())));
        }
        if idx.iter().any(|&x| x < 0 || x > u32::MAX as i64) {
            return Err(perr(format!("face {i} has a negative vertex index")));
        }
        for k in 1..idx.len() - 1 {
            mesh.triangles
                .push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
        }
    }
    Ok(mesh)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A unit cube [0,1]³ as 12 outward triangles.
    pub(crate) fn cube() -> TriMesh {
        let v = |x: f64, y: f64, z: f64| Vector3::new(x, y, z);
        TriMesh {
            vertices: vec![
                v(0., 0., 0.),
                v(1., 0., 0.),
                v(1., 1., 0.),
                v(0., 1., 0.),
                v(0., 0., 1.),
                v(1., 0., 1.),
                v(1., 1., 1.),
                v(0., 1., 1.),
            ],
            triangles: vec![
                [0, 3, 2],
                [0, 2, 1],
                [4, 5, 6],
                [4, 6, 7],
                [0, 1, 5],
                [0, 5, 4],
                [1, 2, 6],
                [1, 6, 5],
                [2, 3, 7],
                [2, 7, 6],
                [3, 0, 4],
                [3, 4, 7],
            ],
        }
    }

    #[test]
    fn cube_checks() {
        let mut m = cube();
        assert!(m.is_closed());
        assert!(m.is_consistently_oriented());
        assert!(m.is_outward_oriented());
        assert!((m.signed_volume() - 1.0).abs() < 1e-12);
        assert!((m.area() - 6.0).abs() < 1e-12);
        let bb = m.bounding_box().unwrap();
        assert_eq!(bb.min, Vector3::zeros());
        assert_eq!(bb.max, Vector3::new(1., 1., 1.));
        assert!(m.contains(&Vector3::new(0.5, 0.5, 0.5)));
        assert!(!m.contains(&Vector3::new(1.5, 0.5, 0.5)));
        m.flip();
        assert!(m.is_consistently_oriented());
        assert!(!m.is_outward_oriented());
        assert!((m.signed_volume() + 1.0).abs() < 1e-12);
        // flip one triangle: still closed, no longer consistent
        let mut m = cube();
        m.triangles[0].swap(1, 2);
        assert!(m.is_closed());
        assert!(!m.is_consistently_oriented());
        // remove one: open
        let mut m = cube();
        m.triangles.pop();
        assert!(!m.is_closed());
        assert_eq!(m.non_manifold_or_boundary_edges(), 3);
    }

    #[test]
    fn obj_roundtrip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.obj");
        cube().write_obj(&p).unwrap();
        let m = TriMesh::load(&p).unwrap();
        assert_ne!(m.vertices, cube().vertices, "tobj renumbers by first use");
        assert_eq!(m, cube().renumbered_by_first_use());
        let mut again = Vec::new();
        m.write_obj_to(&mut again, 9, "").unwrap();
        let m2 = TriMesh::from_bytes(&again, MeshFormat::Obj, Path::new("again.obj")).unwrap();
        assert_eq!(m2, m, "a renumbered mesh round-trips exactly");
    }

    #[test]
    fn obj_quads_are_triangulated_and_groups_merged() {
        let text = "o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\no b\nv 0 0 1\nv 1 0 1\nv 1 1 1\nf 5 6 7\n";
        let m = TriMesh::from_bytes(text.as_bytes(), MeshFormat::Obj, Path::new("q.obj")).unwrap();
        assert_eq!(m.vertices.len(), 7);
        assert_eq!(m.triangles.len(), 3);
        assert_eq!(m.triangles[2], [4, 5, 6]);
    }

    fn stl_ascii(m: &TriMesh) -> String {
        let mut s = String::from("solid cube\n");
        for t in &m.triangles {
            s += "facet normal 0 0 0\nouter loop\n";
            for &i in t {
                let v = m.vertices[i as usize];
                s += &format!("vertex {} {} {}\n", v.x, v.y, v.z);
            }
            s += "endloop\nendfacet\n";
        }
        s + "endsolid cube\n"
    }

    #[test]
    fn stl_ascii_and_binary_merge_vertices() {
        let c = cube();
        let m = TriMesh::from_bytes(
            stl_ascii(&c).as_bytes(),
            MeshFormat::Stl,
            Path::new("c.stl"),
        )
        .unwrap();
        assert_eq!(m.vertices.len(), 8);
        assert_eq!(m.triangles.len(), 12);
        assert!(m.is_outward_oriented());
        assert!((m.signed_volume() - 1.0).abs() < 1e-6);

        let tris: Vec<stl_io::Triangle> = c
            .triangles
            .iter()
            .map(|t| stl_io::Triangle {
                normal: stl_io::Normal::new([0.0; 3]),
                vertices: t.map(|i| {
                    let v = c.vertices[i as usize];
                    stl_io::Vertex::new([v.x as f32, v.y as f32, v.z as f32])
                }),
            })
            .collect();
        let mut bin = Vec::new();
        stl_io::write_stl(&mut bin, tris.iter()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.STL");
        std::fs::write(&p, &bin).unwrap();
        let m = TriMesh::load(&p).unwrap();
        assert_eq!(m.vertices.len(), 8);
        assert!(m.is_outward_oriented());
    }

    #[test]
    fn ply_ascii_and_binary() {
        let c = cube();
        let mut ascii = format!(
            "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
            c.vertices.len(),
            6
        );
        for v in &c.vertices {
            ascii += &format!("{} {} {}\n", v.x, v.y, v.z);
        }
        // write quads (pairs of triangles) to exercise fan triangulation
        for q in c.triangles.chunks(2) {
            // [a,b,c] + [a,c,d] -> quad a b c d
            ascii += &format!("4 {} {} {} {}\n", q[0][0], q[0][1], q[0][2], q[1][2]);
        }
        let m = TriMesh::from_bytes(ascii.as_bytes(), MeshFormat::Ply, Path::new("c.ply")).unwrap();
        assert_eq!(m.triangles.len(), 12);
        assert!(m.is_outward_oriented());
        assert!((m.signed_volume() - 1.0).abs() < 1e-12);

        let mut bin = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            c.vertices.len(),
            c.triangles.len()
        )
        .into_bytes();
        for v in &c.vertices {
            for k in 0..3 {
                bin.extend_from_slice(&v[k].to_le_bytes());
            }
        }
        for t in &c.triangles {
            bin.push(3);
            for &i in t {
                bin.extend_from_slice(&i.to_le_bytes());
            }
        }
        let m = TriMesh::from_bytes(&bin, MeshFormat::Ply, Path::new("c.ply")).unwrap();
        assert_eq!(m, c);
    }

    #[test]
    fn errors_name_file_and_problem() {
        let e = TriMesh::load("/nonexistent/x.obj").unwrap_err().to_string();
        assert!(e.contains("/nonexistent/x.obj"), "{e}");
        let e = TriMesh::load("mesh.vtk").unwrap_err().to_string();
        assert!(e.contains("mesh.vtk: unsupported mesh format"), "{e}");
        let e = TriMesh::from_bytes(b"v 0 0 0\nf 1 2 3\n", MeshFormat::Obj, Path::new("bad.obj"))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("bad.obj: not a valid OBJ file"), "{e}");
        let e = TriMesh::from_bytes(b"v 0 0 0\n", MeshFormat::Obj, Path::new("empty.obj"))
            .unwrap_err()
            .to_string();
        assert_eq!(e, "empty.obj: mesh has no triangles");
        let e = TriMesh::from_bytes(
            b"solid x\nfacet nonsense\n",
            MeshFormat::Stl,
            Path::new("b.stl"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("b.stl: not a valid STL file"), "{e}");
        let e = TriMesh::from_bytes(
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
            MeshFormat::Ply,
            Path::new("b.ply"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("b.ply: not a valid PLY file"), "{e}");
        assert!(e.contains("`y`") || e.contains("face"), "{e}");
    }

    #[test]
    fn fmt_fixed_has_no_negative_zero() {
        assert_eq!(fmt_fixed(-0.000001, 5), "0.00000");
        assert_eq!(fmt_fixed(-0.5, 2), "-0.50");
        assert_eq!(fmt_fixed(1.0 / 3.0, 5), "0.33333");
    }
}
