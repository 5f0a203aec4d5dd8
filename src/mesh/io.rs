//! Mesh and point-cloud files: OBJ (read through tobj), PLY ascii and binary little-endian
//! (read and write), OFF (read); files are opened through [`crate::files`].
//!
//! Every reader has a `*_bytes(name, bytes)` form that takes the file's content, so the
//! property tests can feed random bytes; `name` only labels the errors.

use super::{Mesh, V3};
use crate::files::read_limited;
pub use crate::files::{FileError, write_atomic};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt::Write as _;
use std::path::Path;

fn line_err(path: &str, line: usize, msg: impl Into<String>) -> FileError {
    FileError::line(path, line, msg)
}
fn content_err(path: &str, msg: impl Into<String>) -> FileError {
    FileError::content(path, msg)
}

/// Reads a mesh or point cloud, choosing the reader by the file's extension.
///
/// Example: `let scan = conformd::mesh::read_mesh("scan.ply".as_ref())?;`
pub fn read_mesh(path: &Path) -> Result<Mesh, FileError> {
    let bytes = read_limited(path, MAX_MESH_BYTES)?;
    mesh_from_bytes(path, &bytes)
}

/// [`read_mesh`] of bytes already read (from a folder opened without following links):
/// the reader chosen by `path`'s extension, which also names the file in errors.
pub fn mesh_from_bytes(path: &Path, bytes: &[u8]) -> Result<Mesh, FileError> {
    let name = path.display().to_string();
    let ext = extension(path);
    let mesh = match ext.as_str() {
        "ply" => read_ply_bytes(&name, bytes),
        "obj" => read_obj_bytes(&name, bytes),
        "off" => read_off_bytes(&name, bytes),
        _ => Err(FileError::Format { path: name.clone() }),
    }?;
    // held here, not in the format readers: a coordinate of 1e300 is valid PLY
    mesh.check_coordinates("the mesh")
        .map_err(|e| content_err(&name, e.to_string()))?;
    Ok(mesh)
}

/// Largest mesh file read: a 20M-point binary PLY with normals; a device, a stream or a
/// runaway file is refused instead of read until memory runs out.
pub const MAX_MESH_BYTES: u64 = 1 << 30;

/// Writes `.ply` (binary little-endian) or `.obj`, atomically.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> Result<(), FileError> {
    let bytes = match extension(path).as_str() {
        "ply" => ply_bytes(mesh, PlyEncoding::BinaryLittleEndian),
        "obj" => obj_bytes(mesh).into_bytes(),
        _ => {
            return Err(FileError::Format {
                path: path.display().to_string(),
            });
        }
    };
    write_atomic(path, &bytes)
}

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

// ---------------------------------------------------------------- PLY

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyEncoding {
    Ascii,
    BinaryLittleEndian,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn read_le(self, b: &[u8]) -> f64 {
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::U32 => u32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::F32 => f32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::F64 => f64::from_le_bytes(b[..8].try_into().unwrap()),
        }
    }
}

#[derive(Debug, Clone)]
enum Property {
    Scalar {
        name: String,
        ty: Scalar,
    },
    List {
        name: String,
        count: Scalar,
        item: Scalar,
    },
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

/// Upper bound on element counts, so a corrupt header cannot ask for terabytes.
const MAX_ELEMENTS: usize = 200_000_000;

/// Reads a PLY mesh or point cloud (ascii or binary little-endian). Vertex properties
/// `x y z` are required, `nx ny nz` are kept when present; faces (`vertex_indices` or
/// `vertex_index`) with more than three corners are fan-triangulated.
pub fn read_ply_bytes(path: &str, bytes: &[u8]) -> Result<Mesh, FileError> {
    let PlyHeader {
        encoding,
        elements,
        lines: header_lines,
        body_start,
    } = read_ply_header(path, bytes)?;
    let body = &bytes[body_start..];
    let mut rows: Box<dyn RowSource> = match encoding {
        PlyEncoding::Ascii => Box::new(AsciiRows::new(body, header_lines)),
        PlyEncoding::BinaryLittleEndian => Box::new(BinaryRows { body, pos: 0 }),
    };

    let mut mesh = Mesh::default();
    let mut normals: Vec<V3> = Vec::new();
    let mut has_normals = false;
    let mut seen_vertex = false;
    for el in &elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        let col = |n: &str| {
            el.props
                .iter()
                .position(|p| matches!(p, Property::Scalar { name, .. } if name == n))
        };
        let (cx, cy, cz) = (col("x"), col("y"), col("z"));
        let (cnx, cny, cnz) = (col("nx"), col("ny"), col("nz"));
        let face_list = el.props.iter().position(|p| {
            matches!(p, Property::List { name, .. } if name == "vertex_indices" || name == "vertex_index")
        });
        if is_vertex {
            if cx.is_none() || cy.is_none() || cz.is_none() {
                return Err(content_err(
                    path,
                    "element 'vertex' lacks an x, y or z property",
                ));
            }
            seen_vertex = true;
            has_normals = cnx.is_some() && cny.is_some() && cnz.is_some();
            mesh.vertices.reserve(el.count.min(1 << 24));
        }
        if is_face && face_list.is_none() {
            return Err(content_err(
                path,
                "element 'face' lacks a vertex_indices list",
            ));
        }
        let mut scalars = vec![0.0f64; el.props.len()];
        let mut list: Vec<f64> = Vec::new();
        for row in 0..el.count {
            let what = || format!("element '{}' row {}", el.name, row);
            read_row(rows.as_mut(), el, face_list, &mut scalars, &mut list)
                .map_err(|m| content_err(path, format!("{}: {m}", what())))?;
            if is_vertex {
                let v = V3::new(
                    scalars[cx.unwrap()],
                    scalars[cy.unwrap()],
                    scalars[cz.unwrap()],
                );
                if !v.iter().all(|c| c.is_finite()) {
                    return Err(content_err(
                        path,
                        format!("vertex {row}: non-finite coordinate"),
                    ));
                }
                mesh.vertices.push(v);
                if has_normals {
                    normals.push(V3::new(
                        scalars[cnx.unwrap()],
                        scalars[cny.unwrap()],
                        scalars[cnz.unwrap()],
                    ));
                }
            } else if is_face {
                if list.len() < 3 {
                    return Err(content_err(
                        path,
                        format!("face {row}: fewer than 3 vertices"),
                    ));
                }
                push_polygon(&mut mesh.triangles, &list, mesh.vertices.len(), seen_vertex)
                    .map_err(|m| content_err(path, format!("face {row}: {m}")))?;
            }
        }
    }
    rows.finish()
        .map_err(|m| content_err(path, m.to_string()))?;
    if !seen_vertex {
        return Err(content_err(path, "no 'vertex' element"));
    }
    if has_normals {
        for n in &mut normals {
            let l = n.norm();
            if l.is_finite() && l > 0.0 {
                *n /= l;
            } else {
                *n = V3::zeros();
            }
        }
        mesh.normals = Some(normals);
    }
    Ok(mesh)
}

/// A PLY header: the body's encoding, its elements, how many lines it took, and where
/// the body starts.
struct PlyHeader {
    encoding: PlyEncoding,
    elements: Vec<Element>,
    lines: usize,
    body_start: usize,
}

/// Reads the ascii header lines up to `end_header`.
fn read_ply_header(path: &str, bytes: &[u8]) -> Result<PlyHeader, FileError> {
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut next_line = |pos: &mut usize| -> Option<String> {
        if *pos >= bytes.len() {
            return None;
        }
        let end = bytes[*pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |e| *pos + e);
        let line = String::from_utf8_lossy(&bytes[*pos..end])
            .trim_end_matches('\r')
            .to_string();
        *pos = (end + 1).min(bytes.len());
        line_no += 1;
        Some(line)
    };
    if next_line(&mut pos).as_deref().map(str::trim) != Some("ply") {
        return Err(line_err(
            path,
            1,
            "not a PLY file (the first line must be 'ply')",
        ));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut header_lines = 1;
    loop {
        let Some(line) = next_line(&mut pos) else {
            return Err(content_err(path, "header ends before 'end_header'"));
        };
        header_lines += 1;
        let tok: Vec<&str> = line.split_whitespace().collect();
        match tok.first().copied() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                encoding = Some(match tok.get(1).copied() {
                    Some("ascii") => PlyEncoding::Ascii,
                    Some("binary_little_endian") => PlyEncoding::BinaryLittleEndian,
                    Some(other) => {
                        return Err(line_err(
                            path,
                            header_lines,
                            format!(
                                "format '{other}' is not supported (ascii or binary_little_endian)"
                            ),
                        ));
                    }
                    None => {
                        return Err(line_err(path, header_lines, "format line without a format"));
                    }
                })
            }
            Some("element") => {
                let (Some(name), Some(count)) = (tok.get(1), tok.get(2)) else {
                    return Err(line_err(
                        path,
                        header_lines,
                        "element line needs a name and a count",
                    ));
                };
                let count: usize = count
                    .parse()
                    .ok()
                    .filter(|&c| c <= MAX_ELEMENTS)
                    .ok_or_else(|| {
                        line_err(
                            path,
                            header_lines,
                            format!("element '{name}' has a bad count '{count}'"),
                        )
                    })?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: vec![],
                });
            }
            Some("property") => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| line_err(path, header_lines, "property before any element"))?;
                let prop = parse_property(&tok).ok_or_else(|| {
                    line_err(
                        path,
                        header_lines,
                        format!("malformed property line '{line}'"),
                    )
                })?;
                el.props.push(prop);
            }
            Some("end_header") => break,
            Some(other) => {
                return Err(line_err(
                    path,
                    header_lines,
                    format!("unknown header keyword '{other}'"),
                ));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| content_err(path, "header has no 'format' line"))?;
    Ok(PlyHeader {
        encoding,
        elements,
        lines: header_lines,
        body_start: pos,
    })
}

/// A header's `property` line, split into words: a scalar (`property TYPE NAME`) or a
/// list (`property list COUNT_TYPE ITEM_TYPE NAME`); `None` when malformed.
fn parse_property(tok: &[&str]) -> Option<Property> {
    if tok.get(1) == Some(&"list") {
        let count = tok.get(2).and_then(|s| Scalar::parse(s))?;
        let item = tok.get(3).and_then(|s| Scalar::parse(s))?;
        let name = tok.get(4)?.to_string();
        Some(Property::List { name, count, item })
    } else {
        let ty = tok.get(1).and_then(|s| Scalar::parse(s))?;
        Some(Property::Scalar {
            name: tok.get(2)?.to_string(),
            ty,
        })
    }
}

/// One row of `el`: its scalar properties into `scalars` (by property index), the
/// list property `keep_list` into `list` (other lists are read past).
fn read_row(
    rows: &mut dyn RowSource,
    el: &Element,
    keep_list: Option<usize>,
    scalars: &mut [f64],
    list: &mut Vec<f64>,
) -> Result<(), BodyError> {
    rows.start_row()?;
    for (k, p) in el.props.iter().enumerate() {
        match p {
            Property::Scalar { ty, .. } => scalars[k] = rows.value(*ty)?,
            Property::List { count, item, .. } => {
                let n = rows.value(*count)?;
                if !(0.0..=1_000_000.0).contains(&n) || n.fract() != 0.0 {
                    return Err(BodyError::ListLength(n));
                }
                let keep = Some(k) == keep_list;
                if keep {
                    list.clear();
                }
                for _ in 0..n as usize {
                    let v = rows.value(*item)?;
                    if keep {
                        list.push(v);
                    }
                }
            }
        }
    }
    rows.end_row()
}

/// Fan-triangulates one polygon of vertex indices, checking each index against `nv`.
fn push_polygon(
    out: &mut Vec<[u32; 3]>,
    idx: &[f64],
    nv: usize,
    have_vertices: bool,
) -> Result<(), BodyError> {
    if !have_vertices {
        return Err(BodyError::FacesFirst);
    }
    let mut ids = Vec::with_capacity(idx.len());
    for &i in idx {
        if i < 0.0 || i.fract() != 0.0 || i >= nv as f64 {
            return Err(BodyError::Index {
                index: i,
                vertices: nv,
            });
        }
        ids.push(i as u32);
    }
    for k in 1..ids.len() - 1 {
        out.push([ids[0], ids[k], ids[k + 1]]);
    }
    Ok(())
}

/// What is wrong in a PLY file's body (the header's own errors name their line).
#[derive(Debug, thiserror::Error)]
enum BodyError {
    #[error("file is truncated")]
    Truncated,
    #[error("file is truncated (line {0} is incomplete)")]
    Incomplete(usize),
    #[error("line {0}: too few values")]
    TooFew(usize),
    #[error("line {line}: '{token}' is not a number")]
    NotANumber { line: usize, token: String },
    #[error("line {line}: '{token}' is not an integer")]
    NotAnInteger { line: usize, token: String },
    #[error("line {line}: {got} values, expected {expected}")]
    ValueCount {
        line: usize,
        got: usize,
        expected: usize,
    },
    #[error("ascii body is not valid text")]
    NotText,
    #[error("{0} bytes follow the last element the header declares: the header's counts are wrong")]
    TrailingBytes(usize),
    #[error(
        "line {0}: data after the last element the header declares: the header's counts are wrong"
    )]
    TrailingLine(usize),
    #[error("bad list length {0}")]
    ListLength(f64),
    #[error("faces come before the vertices")]
    FacesFirst,
    #[error("vertex index {index} out of range (the mesh has {vertices} vertices)")]
    Index { index: f64, vertices: usize },
}

trait RowSource {
    fn start_row(&mut self) -> Result<(), BodyError>;
    fn value(&mut self, ty: Scalar) -> Result<f64, BodyError>;
    fn end_row(&mut self) -> Result<(), BodyError>;
    fn finish(&mut self) -> Result<(), BodyError>;
}

struct BinaryRows<'a> {
    body: &'a [u8],
    pos: usize,
}

impl RowSource for BinaryRows<'_> {
    fn start_row(&mut self) -> Result<(), BodyError> {
        Ok(())
    }
    fn value(&mut self, ty: Scalar) -> Result<f64, BodyError> {
        let n = ty.size();
        if self.pos + n > self.body.len() {
            return Err(BodyError::Truncated);
        }
        let v = ty.read_le(&self.body[self.pos..self.pos + n]);
        self.pos += n;
        Ok(v)
    }
    fn end_row(&mut self) -> Result<(), BodyError> {
        Ok(())
    }
    fn finish(&mut self) -> Result<(), BodyError> {
        // more data than the header declares: the counts are wrong, the file is not what
        // it says
        match self.body.len() - self.pos.min(self.body.len()) {
            0 => Ok(()),
            n => Err(BodyError::TrailingBytes(n)),
        }
    }
}

struct AsciiRows<'a> {
    lines: std::iter::Peekable<std::iter::Enumerate<std::str::Lines<'a>>>,
    header_lines: usize,
    tokens: Vec<&'a str>,
    next: usize,
    line: usize,
    invalid_utf8: bool,
}

impl<'a> AsciiRows<'a> {
    fn new(body: &'a [u8], header_lines: usize) -> Self {
        let (text, invalid_utf8) = match std::str::from_utf8(body) {
            Ok(t) => (t, false),
            Err(_) => ("", true),
        };
        AsciiRows {
            lines: text.lines().enumerate().peekable(),
            header_lines,
            tokens: vec![],
            next: 0,
            line: 0,
            invalid_utf8,
        }
    }
}

impl RowSource for AsciiRows<'_> {
    fn start_row(&mut self) -> Result<(), BodyError> {
        if self.invalid_utf8 {
            return Err(BodyError::NotText);
        }
        loop {
            let Some((i, l)) = self.lines.next() else {
                return Err(BodyError::Truncated);
            };
            self.line = self.header_lines + i + 1;
            if !l.trim().is_empty() {
                self.tokens = l.split_whitespace().collect();
                self.next = 0;
                return Ok(());
            }
        }
    }
    fn value(&mut self, ty: Scalar) -> Result<f64, BodyError> {
        let Some(t) = self.tokens.get(self.next) else {
            let last = self.lines.peek().is_none();
            return Err(if last {
                BodyError::Incomplete(self.line)
            } else {
                BodyError::TooFew(self.line)
            });
        };
        self.next += 1;
        let v: f64 = t.parse().map_err(|_| BodyError::NotANumber {
            line: self.line,
            token: t.to_string(),
        })?;
        if !matches!(ty, Scalar::F32 | Scalar::F64) && v.fract() != 0.0 {
            return Err(BodyError::NotAnInteger {
                line: self.line,
                token: t.to_string(),
            });
        }
        Ok(v)
    }
    fn end_row(&mut self) -> Result<(), BodyError> {
        if self.next != self.tokens.len() {
            return Err(BodyError::ValueCount {
                line: self.line,
                got: self.tokens.len(),
                expected: self.next,
            });
        }
        Ok(())
    }
    fn finish(&mut self) -> Result<(), BodyError> {
        for (i, l) in self.lines.by_ref() {
            if !l.trim().is_empty() {
                return Err(BodyError::TrailingLine(self.header_lines + i + 1));
            }
        }
        Ok(())
    }
}

/// Serialises a mesh (or point cloud, with normals if present) as PLY.
pub fn ply_bytes(mesh: &Mesh, enc: PlyEncoding) -> Vec<u8> {
    let normals = mesh
        .normals
        .as_ref()
        .filter(|n| n.len() == mesh.vertices.len());
    let mut h = String::new();
    h.push_str("ply\n");
    h.push_str(match enc {
        PlyEncoding::Ascii => "format ascii 1.0\n",
        PlyEncoding::BinaryLittleEndian => "format binary_little_endian 1.0\n",
    });
    h.push_str("comment written by conformd\n");
    let _ = writeln!(h, "element vertex {}", mesh.vertices.len());
    h.push_str("property double x\nproperty double y\nproperty double z\n");
    if normals.is_some() {
        h.push_str("property double nx\nproperty double ny\nproperty double nz\n");
    }
    if !mesh.triangles.is_empty() {
        let _ = writeln!(h, "element face {}", mesh.triangles.len());
        h.push_str("property list uchar int vertex_indices\n");
    }
    h.push_str("end_header\n");
    let mut out = h.into_bytes();
    match enc {
        PlyEncoding::Ascii => {
            let mut s = String::new();
            for (i, v) in mesh.vertices.iter().enumerate() {
                let _ = write!(s, "{} {} {}", v.x, v.y, v.z);
                if let Some(n) = normals {
                    let _ = write!(s, " {} {} {}", n[i].x, n[i].y, n[i].z);
                }
                s.push('\n');
            }
            for t in &mesh.triangles {
                let _ = writeln!(s, "3 {} {} {}", t[0], t[1], t[2]);
            }
            out.extend_from_slice(s.as_bytes());
        }
        PlyEncoding::BinaryLittleEndian => {
            out.reserve(mesh.vertices.len() * 48 + mesh.triangles.len() * 13);
            for (i, v) in mesh.vertices.iter().enumerate() {
                for c in v.iter() {
                    out.extend_from_slice(&c.to_le_bytes());
                }
                if let Some(n) = normals {
                    for c in n[i].iter() {
                        out.extend_from_slice(&c.to_le_bytes());
                    }
                }
            }
            for t in &mesh.triangles {
                out.push(3);
                for &i in t {
                    out.extend_from_slice(&(i as i32).to_le_bytes());
                }
            }
        }
    }
    out
}

// ---------------------------------------------------------------- OBJ

/// Reads an OBJ through tobj: polygons are triangulated, `o`/`g` groups become named
/// vertex groups. Vertices keep the file's order (tobj renumbers them per group; they are
/// mapped back by position), so vertex i of the mesh is the file's i-th `v` line.
pub fn read_obj_bytes(path: &str, bytes: &[u8]) -> Result<Mesh, FileError> {
    // The file's own vertex list, in order, for mapping tobj's renumbering back.
    let text = std::str::from_utf8(bytes).map_err(|e| {
        content_err(
            path,
            format!(
                "not a text file (invalid UTF-8 at byte {})",
                e.valid_up_to()
            ),
        )
    })?;
    let mut file_vertices: Vec<V3> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let mut tok = line.split_whitespace();
        if tok.next() == Some("v") {
            let c: Vec<f64> = tok
                .take(3)
                .map(|t| t.parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| {
                    line_err(path, i + 1, "a 'v' line with a value that is not a number")
                })?;
            if c.len() < 3 {
                return Err(line_err(
                    path,
                    i + 1,
                    "a 'v' line with fewer than 3 coordinates",
                ));
            }
            if !c.iter().all(|x| x.is_finite()) {
                return Err(line_err(path, i + 1, "non-finite vertex coordinate"));
            }
            file_vertices.push(V3::new(c[0], c[1], c[2]));
        }
    }
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ..Default::default()
    };
    let (models, _) = tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &opts, |_| {
        Err(tobj::LoadError::GenericFailure)
    })
    .map_err(|e| content_err(path, format!("OBJ parse error: {e}")))?;

    let key = |v: &V3| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()];
    let mut by_pos: HashMap<[u64; 3], Vec<u32>> = HashMap::new();
    for (i, v) in file_vertices.iter().enumerate() {
        by_pos.entry(key(v)).or_default().push(i as u32);
    }
    let mut mesh = Mesh::new(file_vertices, Vec::new());
    let mut groups: BTreeMap<String, BTreeSet<u32>> = BTreeMap::new();
    for m in &models {
        let p = &m.mesh.positions;
        if p.len() % 3 != 0 || m.mesh.indices.len() % 3 != 0 {
            return Err(content_err(
                path,
                format!("group '{}': malformed geometry", m.name),
            ));
        }
        // tobj vertex k of this model -> file vertex index
        let mut used: HashMap<[u64; 3], usize> = HashMap::new();
        let mut map = Vec::with_capacity(p.len() / 3);
        for k in 0..p.len() / 3 {
            let v = V3::new(p[3 * k], p[3 * k + 1], p[3 * k + 2]);
            let kk = key(&v);
            let cands = by_pos.get(&kk).ok_or_else(|| {
                content_err(
                    path,
                    format!(
                        "group '{}': a face refers to a vertex that is not in the file",
                        m.name
                    ),
                )
            })?;
            let n = used.entry(kk).or_insert(0);
            map.push(cands[(*n).min(cands.len() - 1)]);
            *n += 1;
        }
        for t in m.mesh.indices.chunks_exact(3) {
            let tri = [t[0], t[1], t[2]].map(|i| map.get(i as usize).copied());
            let [Some(a), Some(b), Some(c)] = tri else {
                return Err(content_err(
                    path,
                    format!("group '{}': face index out of range", m.name),
                ));
            };
            mesh.triangles.push([a, b, c]);
            if !m.name.is_empty() && m.name != "unnamed_object" {
                groups.entry(m.name.clone()).or_default().extend([a, b, c]);
            }
        }
    }
    mesh.groups = groups
        .into_iter()
        .map(|(k, v)| (k, v.into_iter().collect()))
        .collect();
    Ok(mesh)
}

/// Serialises a mesh as OBJ text (vertices, normals if present, triangles, 1-based).
/// Vertex groups are written as `g` lines: a triangle belongs to the first group holding
/// all three of its vertices, and a `g` line starts wherever that changes, so triangles
/// keep their order (reading the file back gives each group the vertices of its
/// triangles, so groups gain the vertices along their borders).
pub fn obj_bytes(mesh: &Mesh) -> String {
    let mut s = String::with_capacity(mesh.vertices.len() * 40 + mesh.triangles.len() * 24);
    s.push_str("# written by conformd\n");
    for v in &mesh.vertices {
        let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
    }
    let normals = mesh
        .normals
        .as_ref()
        .filter(|n| n.len() == mesh.vertices.len());
    if let Some(ns) = normals {
        for n in ns {
            let _ = writeln!(s, "vn {} {} {}", n.x, n.y, n.z);
        }
    }
    let sets: Vec<(&String, std::collections::HashSet<u32>)> = mesh
        .groups
        .iter()
        .map(|(k, v)| (k, v.iter().copied().collect()))
        .collect();
    let group_of = |t: &[u32; 3]| {
        sets.iter()
            .position(|(_, set)| t.iter().all(|i| set.contains(i)))
    };
    let mut current = None;
    for t in &mesh.triangles {
        let g = if sets.is_empty() { None } else { group_of(t) };
        if g != current {
            match g {
                Some(g) => {
                    let _ = writeln!(s, "g {}", sets[g].0);
                }
                None => s.push_str("g\n"),
            }
            current = g;
        }
        let [a, b, c] = t.map(|i| i + 1);
        if normals.is_some() {
            let _ = writeln!(s, "f {a}//{a} {b}//{b} {c}//{c}");
        } else {
            let _ = writeln!(s, "f {a} {b} {c}");
        }
    }
    s
}

// ---------------------------------------------------------------- OFF

/// Reads an OFF file (`OFF` header, counts, vertices, polygons; `#` comments allowed).
pub fn read_off_bytes(path: &str, bytes: &[u8]) -> Result<Mesh, FileError> {
    let text = std::str::from_utf8(bytes).map_err(|_| content_err(path, "not a text file"))?;
    // Tokens with their line numbers, comments stripped.
    let mut toks = text.lines().enumerate().flat_map(|(i, l)| {
        l.split('#')
            .next()
            .unwrap_or("")
            .split_whitespace()
            .map(move |t| (i + 1, t))
    });
    let (l, head) = toks.next().ok_or_else(|| content_err(path, "empty file"))?;
    if head != "OFF" {
        return Err(line_err(path, l, format!("expected 'OFF', found '{head}'")));
    }
    let last_line = std::cell::Cell::new(l);
    let mut num = |what: &str| -> Result<f64, FileError> {
        let (l, t) = toks
            .next()
            .ok_or_else(|| content_err(path, format!("file ends while reading {what}")))?;
        last_line.set(l);
        t.parse::<f64>()
            .map_err(|_| line_err(path, l, format!("{what}: '{t}' is not a number")))
    };
    let count = |x: f64, what: &str| -> Result<usize, FileError> {
        if x < 0.0 || x.fract() != 0.0 || x > MAX_ELEMENTS as f64 {
            return Err(content_err(path, format!("bad {what} count {x}")));
        }
        Ok(x as usize)
    };
    let nv = count(num("vertex count")?, "vertex")?;
    let nf = count(num("face count")?, "face")?;
    let _ne = num("edge count")?;
    let mut mesh = Mesh::default();
    mesh.vertices.reserve(nv.min(1 << 24));
    for i in 0..nv {
        let w = format!("vertex {i}");
        let v = V3::new(num(&w)?, num(&w)?, num(&w)?);
        if !v.iter().all(|c| c.is_finite()) {
            return Err(content_err(
                path,
                format!("vertex {i}: non-finite coordinate"),
            ));
        }
        mesh.vertices.push(v);
    }
    for f in 0..nf {
        let w = format!("face {f}");
        let n = num(&w)?;
        if !(3.0..=1_000_000.0).contains(&n) || n.fract() != 0.0 {
            return Err(line_err(
                path,
                last_line.get(),
                format!("face {f}: bad corner count {n}"),
            ));
        }
        let idx: Vec<f64> = (0..n as usize).map(|_| num(&w)).collect::<Result<_, _>>()?;
        push_polygon(&mut mesh.triangles, &idx, nv, true)
            .map_err(|m| line_err(path, last_line.get(), format!("face {f}: {m}")))?;
        // Per-face colours after the corner list are not supported.
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tet() -> Mesh {
        Mesh::new(
            vec![
                V3::new(0., 0., 0.),
                V3::new(1., 0., 0.),
                V3::new(0., 1., 0.),
                V3::new(0., 0., 1.),
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    }

    #[test]
    fn ply_round_trips_both_encodings() {
        let mut m = tet();
        m.normals = Some(m.vertex_normals());
        for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian] {
            let back = read_ply_bytes("t.ply", &ply_bytes(&m, enc)).unwrap();
            assert_eq!(back.triangles, m.triangles);
            for (a, b) in back.vertices.iter().zip(&m.vertices) {
                assert!((a - b).norm() < 1e-12);
            }
            assert!(back.normals.is_some());
        }
    }

    #[test]
    fn obj_keeps_file_vertex_order_and_groups() {
        let src =
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\ng first\nf 4 2 1\ng second\nf 1 3 4\nf 2 3 4 1\n";
        let m = read_obj_bytes("t.obj", src.as_bytes()).unwrap();
        assert_eq!(m.vertices[3], V3::new(0., 0., 1.));
        assert_eq!(m.triangles[0], [3, 1, 0]);
        assert_eq!(m.triangles.len(), 4, "the quad is split in two");
        assert_eq!(m.groups["first"], vec![0, 1, 3]);
        assert_eq!(m.groups["second"], vec![0, 1, 2, 3]);
    }

    #[test]
    fn off_reads_polygons() {
        let src = "OFF\n# a square\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
        let m = read_off_bytes("t.off", src.as_bytes()).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }
}
