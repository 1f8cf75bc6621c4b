//! Output writers: VTK XML UnstructuredGrid (`.vtu`), ParaView collections (`.pvd`) and OBJ
//! surfaces.
//!
//! Small hand-written writers. VTU data arrays are written either as ASCII or as inline
//! base64 binary (`format="binary"`, uncompressed, little endian, `header_type="UInt64"`:
//! each array is the base64 encoding of an 8-byte byte count followed by the raw values).

use std::borrow::Cow;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{UnitQuaternion, Vector3};

use base64::Engine as _;

use crate::mesh::TriMesh;

/// How data arrays are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Encoding {
    /// Human-readable numbers.
    Ascii,
    /// Inline base64 of little-endian binary (smaller and exact).
    #[default]
    Binary,
}

/// The numbers of a data array.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayData<'a> {
    /// `Float64`.
    F64(Cow<'a, [f64]>),
    /// `Float32`.
    F32(Cow<'a, [f32]>),
    /// `Int32`.
    I32(Cow<'a, [i32]>),
    /// `UInt32`.
    U32(Cow<'a, [u32]>),
    /// `UInt8`.
    U8(Cow<'a, [u8]>),
}

impl ArrayData<'_> {
    fn len(&self) -> usize {
        match self {
            ArrayData::F64(v) => v.len(),
            ArrayData::F32(v) => v.len(),
            ArrayData::I32(v) => v.len(),
            ArrayData::U32(v) => v.len(),
            ArrayData::U8(v) => v.len(),
        }
    }
    fn type_name(&self) -> &'static str {
        match self {
            ArrayData::F64(_) => "Float64",
            ArrayData::F32(_) => "Float32",
            ArrayData::I32(_) => "Int32",
            ArrayData::U32(_) => "UInt32",
            ArrayData::U8(_) => "UInt8",
        }
    }
    fn le_bytes(&self) -> Vec<u8> {
        fn go<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
            v.iter().flat_map(|&x| f(x)).collect()
        }
        match self {
            ArrayData::F64(v) => go(v, f64::to_le_bytes),
            ArrayData::F32(v) => go(v, f32::to_le_bytes),
            ArrayData::I32(v) => go(v, i32::to_le_bytes),
            ArrayData::U32(v) => go(v, u32::to_le_bytes),
            ArrayData::U8(v) => v.to_vec(),
        }
    }
    fn ascii(&self) -> String {
        fn join<T: std::fmt::Display>(v: &[T]) -> String {
            let mut s = String::with_capacity(v.len() * 8);
            for (i, x) in v.iter().enumerate() {
                if i > 0 {
                    s.push(' ');
                }
                s += &x.to_string();
            }
            s
        }
        match self {
            // `Display` of floats is the shortest string that round-trips exactly.
            ArrayData::F64(v) => join(v),
            ArrayData::F32(v) => join(v),
            ArrayData::I32(v) => join(v),
            ArrayData::U32(v) => join(v),
            ArrayData::U8(v) => join(v),
        }
    }
}

/// A named data array with `components` numbers per point or cell.
#[derive(Debug, Clone, PartialEq)]
pub struct DataArray<'a> {
    /// Array name shown by ParaView.
    pub name: String,
    /// Components per tuple (1 = scalar, 3 = vector).
    pub components: usize,
    /// The values, `components` per tuple.
    pub data: ArrayData<'a>,
}

impl<'a> DataArray<'a> {
    /// One `f64` per tuple.
    pub fn scalars(name: &str, v: &'a [f64]) -> Self {
        Self {
            name: name.into(),
            components: 1,
            data: ArrayData::F64(Cow::Borrowed(v)),
        }
    }
    /// Three `f64` per tuple.
    pub fn vectors(name: &str, v: &[Vector3<f64>]) -> DataArray<'static> {
        DataArray {
            name: name.into(),
            components: 3,
            data: ArrayData::F64(Cow::Owned(v.iter().flat_map(|p| [p.x, p.y, p.z]).collect())),
        }
    }
    /// One `i32` per tuple (levels, types, material ids, ...).
    pub fn ints(name: &str, v: &'a [i32]) -> Self {
        Self {
            name: name.into(),
            components: 1,
            data: ArrayData::I32(Cow::Borrowed(v)),
        }
    }
    /// One `u32` per tuple (tree ids, node ids, ...).
    pub fn uints(name: &str, v: &'a [u32]) -> Self {
        Self {
            name: name.into(),
            components: 1,
            data: ArrayData::U32(Cow::Borrowed(v)),
        }
    }
    /// One `u8` per tuple (flags).
    pub fn bytes(name: &str, v: &'a [u8]) -> Self {
        Self {
            name: name.into(),
            components: 1,
            data: ArrayData::U8(Cow::Borrowed(v)),
        }
    }
    fn tuples(&self) -> usize {
        self.data.len() / self.components.max(1)
    }
}

/// Cell connectivity of an unstructured grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Cells<'a> {
    /// Linear tetrahedra (VTK type 10).
    Tets(&'a [[u32; 4]]),
    /// Triangles (VTK type 5).
    Triangles(&'a [[u32; 3]]),
    /// One vertex cell (VTK type 1) per point.
    Points,
}

impl Cells<'_> {
    fn count(&self, n_points: usize) -> usize {
        match self {
            Cells::Tets(t) => t.len(),
            Cells::Triangles(t) => t.len(),
            Cells::Points => n_points,
        }
    }
}

/// One VTU piece: points, cells and attached data.
#[derive(Debug, Clone)]
pub struct UnstructuredGrid<'a> {
    /// Point positions (m).
    pub points: &'a [Vector3<f64>],
    /// Cells.
    pub cells: Cells<'a>,
    /// Per-point arrays (each with `points.len()` tuples).
    pub point_data: Vec<DataArray<'a>>,
    /// Per-cell arrays (each with one tuple per cell).
    pub cell_data: Vec<DataArray<'a>>,
}

impl<'a> UnstructuredGrid<'a> {
    /// A grid without data arrays.
    pub fn new(points: &'a [Vector3<f64>], cells: Cells<'a>) -> Self {
        Self {
            points,
            cells,
            point_data: Vec::new(),
            cell_data: Vec::new(),
        }
    }
    /// Adds a point array.
    pub fn with_point_data(mut self, a: DataArray<'a>) -> Self {
        self.point_data.push(a);
        self
    }
    /// Adds a cell array.
    pub fn with_cell_data(mut self, a: DataArray<'a>) -> Self {
        self.cell_data.push(a);
        self
    }
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn invalid(msg: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidInput, msg)
}

fn write_array<W: Write>(
    w: &mut W,
    a: &DataArray<'_>,
    enc: Encoding,
    indent: &str,
) -> std::io::Result<()> {
    let comps = if a.components > 1 {
        format!(" NumberOfComponents=\"{}\"", a.components)
    } else {
        String::new()
    };
    let name = xml_escape(&a.name);
    let ty = a.data.type_name();
    match enc {
        Encoding::Ascii => {
            writeln!(
                w,
                "{indent}<DataArray type=\"{ty}\" Name=\"{name}\"{comps} format=\"ascii\">"
            )?;
            writeln!(w, "{indent}  {}", a.data.ascii())?;
        }
        Encoding::Binary => {
            writeln!(
                w,
                "{indent}<DataArray type=\"{ty}\" Name=\"{name}\"{comps} format=\"binary\">"
            )?;
            let body = a.data.le_bytes();
            let mut buf = (body.len() as u64).to_le_bytes().to_vec();
            buf.extend_from_slice(&body);
            writeln!(
                w,
                "{indent}  {}",
                base64::engine::general_purpose::STANDARD.encode(&buf)
            )?;
        }
    }
    writeln!(w, "{indent}</DataArray>")
}

/// Writes a VTU document.
pub fn write_vtu<W: Write>(
    w: &mut W,
    grid: &UnstructuredGrid<'_>,
    enc: Encoding,
) -> std::io::Result<()> {
    let np = grid.points.len();
    let nc = grid.cells.count(np);
    for a in &grid.point_data {
        if a.tuples() != np || a.data.len() != np * a.components {
            return Err(invalid(format!(
                "point array \"{}\" has {} values, expected {} × {}",
                a.name,
                a.data.len(),
                np,
                a.components
            )));
        }
    }
    for a in &grid.cell_data {
        if a.data.len() != nc * a.components {
            return Err(invalid(format!(
                "cell array \"{}\" has {} values, expected {} × {}",
                a.name,
                a.data.len(),
                nc,
                a.components
            )));
        }
    }
    let (conn, vtk_type, nverts): (Vec<u32>, u8, u32) = match grid.cells {
        Cells::Tets(t) => (t.iter().flatten().copied().collect(), 10, 4),
        Cells::Triangles(t) => (t.iter().flatten().copied().collect(), 5, 3),
        Cells::Points => ((0..np as u32).collect(), 1, 1),
    };
    if let Some(&bad) = conn.iter().find(|&&i| i as usize >= np) {
        return Err(invalid(format!(
            "cell refers to point {bad}, but there are {np} points"
        )));
    }
    let offsets: Vec<u32> = (1..=nc as u32).map(|i| i * nverts).collect();
    let types = vec![vtk_type; nc];
    writeln!(w, "<?xml version=\"1.0\"?>")?;
    writeln!(
        w,
        "<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">"
    )?;
    writeln!(w, "  <UnstructuredGrid>")?;
    writeln!(
        w,
        "    <Piece NumberOfPoints=\"{np}\" NumberOfCells=\"{nc}\">"
    )?;
    let ind = "        ";
    writeln!(w, "      <PointData>")?;
    for a in &grid.point_data {
        write_array(w, a, enc, ind)?;
    }
    writeln!(w, "      </PointData>")?;
    writeln!(w, "      <CellData>")?;
    for a in &grid.cell_data {
        write_array(w, a, enc, ind)?;
    }
    writeln!(w, "      </CellData>")?;
    writeln!(w, "      <Points>")?;
    let pts: Vec<f64> = grid.points.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
    write_array(
        w,
        &DataArray {
            name: "Points".into(),
            components: 3,
            data: ArrayData::F64(Cow::Owned(pts)),
        },
        enc,
        ind,
    )?;
    writeln!(w, "      </Points>")?;
    writeln!(w, "      <Cells>")?;
    for (name, data) in [
        ("connectivity", ArrayData::U32(Cow::Owned(conn))),
        ("offsets", ArrayData::U32(Cow::Owned(offsets))),
        ("types", ArrayData::U8(Cow::Owned(types))),
    ] {
        write_array(
            w,
            &DataArray {
                name: name.into(),
                components: 1,
                data,
            },
            enc,
            ind,
        )?;
    }
    writeln!(w, "      </Cells>")?;
    writeln!(w, "    </Piece>")?;
    writeln!(w, "  </UnstructuredGrid>")?;
    writeln!(w, "</VTKFile>")
}

fn create(path: &Path) -> std::io::Result<std::io::BufWriter<std::fs::File>> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir)?;
    }
    Ok(std::io::BufWriter::new(std::fs::File::create(path)?))
}

fn with_path(path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

/// Writes a `.vtu` file (creating parent directories). Errors name the file.
pub fn write_vtu_file(
    path: impl AsRef<Path>,
    grid: &UnstructuredGrid<'_>,
    enc: Encoding,
) -> std::io::Result<()> {
    let path = path.as_ref();
    (|| {
        let mut w = create(path)?;
        write_vtu(&mut w, grid, enc)?;
        w.flush()
    })()
    .map_err(|e| with_path(path, e))
}

/// Tool poses as a point cloud: one vertex cell per pose with point arrays `axis_x`,
/// `axis_y`, `axis_z` (the rotated unit axes; the shaft is `axis_z`) plus `extra`.
pub fn write_poses_vtu<W: Write>(
    w: &mut W,
    poses: &[(Vector3<f64>, UnitQuaternion<f64>)],
    extra: Vec<DataArray<'_>>,
    enc: Encoding,
) -> std::io::Result<()> {
    let pts: Vec<Vector3<f64>> = poses.iter().map(|p| p.0).collect();
    let axis = |a: Vector3<f64>| -> Vec<Vector3<f64>> { poses.iter().map(|p| p.1 * a).collect() };
    let mut g = UnstructuredGrid::new(&pts, Cells::Points)
        .with_point_data(DataArray::vectors("axis_x", &axis(Vector3::x())))
        .with_point_data(DataArray::vectors("axis_y", &axis(Vector3::y())))
        .with_point_data(DataArray::vectors("axis_z", &axis(Vector3::z())));
    g.point_data.extend(extra);
    write_vtu(w, &g, enc)
}

/// One dataset of a [`Pvd`] collection.
#[derive(Debug, Clone, PartialEq)]
pub struct PvdEntry {
    /// Simulation time in s.
    pub timestep: f64,
    /// Part index (e.g. 0 = volume, 1 = surface, 2 = tools).
    pub part: u32,
    /// File, relative to the `.pvd` file.
    pub file: PathBuf,
}

/// A ParaView collection (`.pvd`): a time series of datasets.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pvd {
    /// The datasets, in the order written.
    pub entries: Vec<PvdEntry>,
}

impl Pvd {
    /// An empty collection.
    pub fn new() -> Self {
        Self::default()
    }
    /// Adds a dataset.
    pub fn push(&mut self, timestep: f64, part: u32, file: impl Into<PathBuf>) {
        self.entries.push(PvdEntry {
            timestep,
            part,
            file: file.into(),
        });
    }
    /// Writes the collection document.
    pub fn write<W: Write>(&self, w: &mut W) -> std::io::Result<()> {
        writeln!(w, "<?xml version=\"1.0\"?>")?;
        writeln!(
            w,
            "<VTKFile type=\"Collection\" version=\"0.1\" byte_order=\"LittleEndian\">"
        )?;
        writeln!(w, "  <Collection>")?;
        for e in &self.entries {
            let file = e.file.to_string_lossy().replace('\\', "/");
            writeln!(
                w,
                "    <DataSet timestep=\"{}\" group=\"\" part=\"{}\" file=\"{}\"/>",
                e.timestep,
                e.part,
                xml_escape(&file)
            )?;
        }
        writeln!(w, "  </Collection>")?;
        writeln!(w, "</VTKFile>")
    }
    /// Writes the collection to a file (creating parent directories).
    pub fn write_file(&self, path: impl AsRef<Path>) -> std::io::Result<()> {
        let path = path.as_ref();
        (|| {
            let mut w = create(path)?;
            self.write(&mut w)?;
            w.flush()
        })()
        .map_err(|e| with_path(path, e))
    }
}

/// Writes a deformed surface as OBJ (`decimals` digits, e.g. 6 = micrometres).
pub fn write_surface_obj(
    path: impl AsRef<Path>,
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    decimals: usize,
    header: &str,
) -> std::io::Result<()> {
    let path = path.as_ref();
    let mesh = TriMesh {
        vertices: vertices.to_vec(),
        triangles: triangles.to_vec(),
    };
    (|| {
        let mut w = create(path)?;
        mesh.write_obj_to(&mut w, decimals, header)?;
        w.flush()
    })()
    .map_err(|e| with_path(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parses a DataArray's text back into f64 values (both encodings).
    fn values(node: roxmltree::Node<'_, '_>) -> Vec<f64> {
        let text = node.text().unwrap_or("").trim();
        let ty = node.attribute("type").unwrap();
        match node.attribute("format").unwrap() {
            "ascii" => text
                .split_whitespace()
                .map(|s| s.parse::<f64>().unwrap())
                .collect(),
            "binary" => {
                let raw = base64::engine::general_purpose::STANDARD
                    .decode(text)
                    .unwrap();
                let n = u64::from_le_bytes(raw[..8].try_into().unwrap()) as usize;
                let body = &raw[8..];
                assert_eq!(n, body.len(), "header byte count");
                match ty {
                    "Float64" => body
                        .chunks_exact(8)
                        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                    "Float32" => body
                        .chunks_exact(4)
                        .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
                        .collect(),
                    "Int32" => body
                        .chunks_exact(4)
                        .map(|c| i32::from_le_bytes(c.try_into().unwrap()) as f64)
                        .collect(),
                    "UInt32" => body
                        .chunks_exact(4)
                        .map(|c| u32::from_le_bytes(c.try_into().unwrap()) as f64)
                        .collect(),
                    "UInt8" => body.iter().map(|&b| b as f64).collect(),
                    t => panic!("type {t}"),
                }
            }
            f => panic!("format {f}"),
        }
    }

    fn array<'a, 'i>(
        doc: &'a roxmltree::Document<'i>,
        parent: &str,
        name: &str,
    ) -> roxmltree::Node<'a, 'i> {
        doc.descendants()
            .find(|n| n.has_tag_name(parent))
            .unwrap()
            .children()
            .find(|n| n.has_tag_name("DataArray") && n.attribute("Name") == Some(name))
            .unwrap_or_else(|| panic!("no {parent}/{name}"))
    }

    #[test]
    fn tet_grid_roundtrip_both_encodings() {
        let points = vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 1.0, 0.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(1.0 / 3.0, 1.0, 1.0e-7),
        ];
        let tets = [[0u32, 1, 2, 3], [1, 2, 3, 4]];
        let disp: Vec<Vector3<f64>> = (0..5)
            .map(|i| Vector3::new(i as f64, -0.1, 0.123456789))
            .collect();
        let level = [0i32, -2];
        let tree = [7u32, 4_000_000_000];
        let mat = [1u8, 2];
        for enc in [Encoding::Ascii, Encoding::Binary] {
            let g = UnstructuredGrid::new(&points, Cells::Tets(&tets))
                .with_point_data(DataArray::vectors("displacement", &disp))
                .with_cell_data(DataArray::ints("level", &level))
                .with_cell_data(DataArray::uints("tree id", &tree))
                .with_cell_data(DataArray::bytes("material", &mat));
            let mut out = Vec::new();
            write_vtu(&mut out, &g, enc).unwrap();
            let text = String::from_utf8(out).unwrap();
            let doc = roxmltree::Document::parse(&text).unwrap();
            let piece = doc.descendants().find(|n| n.has_tag_name("Piece")).unwrap();
            assert_eq!(piece.attribute("NumberOfPoints"), Some("5"));
            assert_eq!(piece.attribute("NumberOfCells"), Some("2"));
            let pts = values(array(&doc, "Points", "Points"));
            let expect: Vec<f64> = points.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
            assert_eq!(pts, expect, "exact round trip ({enc:?})");
            let d = array(&doc, "PointData", "displacement");
            assert_eq!(d.attribute("NumberOfComponents"), Some("3"));
            assert_eq!(
                values(d),
                disp.iter()
                    .flat_map(|p| [p.x, p.y, p.z])
                    .collect::<Vec<_>>()
            );
            assert_eq!(values(array(&doc, "CellData", "level")), [0.0, -2.0]);
            assert_eq!(values(array(&doc, "CellData", "tree id")), [7.0, 4e9]);
            assert_eq!(values(array(&doc, "CellData", "material")), [1.0, 2.0]);
            assert_eq!(
                values(array(&doc, "Cells", "connectivity")),
                [0., 1., 2., 3., 1., 2., 3., 4.]
            );
            assert_eq!(values(array(&doc, "Cells", "offsets")), [4.0, 8.0]);
            assert_eq!(values(array(&doc, "Cells", "types")), [10.0, 10.0]);
        }
    }

    #[test]
    fn surface_and_points() {
        let points = vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 1.0, 0.0),
        ];
        let tris = [[0u32, 1, 2]];
        let f = [0.5, 1.5, 2.5];
        let g = UnstructuredGrid::new(&points, Cells::Triangles(&tris))
            .with_point_data(DataArray::scalars("f", &f));
        let mut out = Vec::new();
        write_vtu(&mut out, &g, Encoding::Binary).unwrap();
        let text = String::from_utf8(out).unwrap();
        let doc = roxmltree::Document::parse(&text).unwrap();
        assert_eq!(values(array(&doc, "Cells", "types")), [5.0]);
        assert_eq!(values(array(&doc, "PointData", "f")), f);

        let q = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2);
        let mut out = Vec::new();
        write_poses_vtu(
            &mut out,
            &[
                (Vector3::new(1.0, 2.0, 3.0), q),
                (Vector3::zeros(), UnitQuaternion::identity()),
            ],
            vec![],
            Encoding::Ascii,
        )
        .unwrap();
        let text = String::from_utf8(out).unwrap();
        let doc = roxmltree::Document::parse(&text).unwrap();
        assert_eq!(values(array(&doc, "Cells", "types")), [1.0, 1.0]);
        assert_eq!(values(array(&doc, "Cells", "connectivity")), [0.0, 1.0]);
        let z = values(array(&doc, "PointData", "axis_z"));
        // x-rotation by 90° maps z to −y
        assert!(
            (z[1] + 1.0).abs() < 1e-12 && z[2].abs() < 1e-12 && z[5] == 1.0,
            "{z:?}"
        );
    }

    #[test]
    fn bad_sizes_are_rejected() {
        let points = vec![Vector3::zeros(); 3];
        let tris = [[0u32, 1, 5]];
        let mut out = Vec::new();
        let e = write_vtu(
            &mut out,
            &UnstructuredGrid::new(&points, Cells::Triangles(&tris)),
            Encoding::Ascii,
        )
        .unwrap_err();
        assert!(e.to_string().contains("refers to point 5"), "{e}");
        let f = [1.0];
        let tris = [[0u32, 1, 2]];
        let g = UnstructuredGrid::new(&points, Cells::Triangles(&tris))
            .with_point_data(DataArray::scalars("f", &f));
        let e = write_vtu(&mut out, &g, Encoding::Ascii).unwrap_err();
        assert!(
            e.to_string()
                .contains("point array \"f\" has 1 values, expected 3"),
            "{e}"
        );
    }

    #[test]
    fn pvd_and_obj_files() {
        let dir = tempfile::tempdir().unwrap();
        let mut pvd = Pvd::new();
        pvd.push(0.0, 0, "frames/vol_0000.vtu");
        pvd.push(0.002, 0, "frames/vol_0001.vtu");
        pvd.push(0.002, 1, "frames/surf_0001.vtu");
        let p = dir.path().join("out/run.pvd");
        pvd.write_file(&p).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        let doc = roxmltree::Document::parse(&text).unwrap();
        let ds: Vec<_> = doc
            .descendants()
            .filter(|n| n.has_tag_name("DataSet"))
            .collect();
        assert_eq!(ds.len(), 3);
        assert_eq!(ds[1].attribute("timestep"), Some("0.002"));
        assert_eq!(ds[2].attribute("part"), Some("1"));
        assert_eq!(ds[2].attribute("file"), Some("frames/surf_0001.vtu"));

        let v = vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 1.0, -0.25),
        ];
        let p = dir.path().join("s.obj");
        write_surface_obj(&p, &v, &[[0, 1, 2]], 6, "t = 0.5 s").unwrap();
        let m = TriMesh::load(&p).unwrap();
        assert_eq!(m.vertices, v);
        assert_eq!(m.triangles, [[0, 1, 2]]);
        assert!(
            std::fs::read_to_string(&p)
                .unwrap()
                .starts_with("# t = 0.5 s\n")
        );

        let e = write_vtu_file(
            "/proc/nonexistent/x.vtu",
            &UnstructuredGrid::new(&v, Cells::Points),
            Encoding::Ascii,
        )
        .unwrap_err();
        assert!(e.to_string().contains("/proc/nonexistent/x.vtu"), "{e}");
    }
}
