//! Vertex group files: one group a line, `name i j k ...` (vertex indices), `#` comments;
//! a name may appear on several lines. Groups let conformation stiffen parts and the
//! shape model analyse one segment.

use super::Mesh;
use crate::files::FileError;
use std::collections::BTreeMap;
use std::path::Path;

/// Parses a groups file, checking every index against `vertices`.
pub fn parse(
    path: &str,
    text: &str,
    vertices: usize,
) -> Result<BTreeMap<String, Vec<u32>>, FileError> {
    let mut out: BTreeMap<String, Vec<u32>> = BTreeMap::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        let mut tok = line.split_whitespace();
        let Some(name) = tok.next() else { continue };
        let err = |msg: String| FileError::line(path, i + 1, msg);
        let set = out.entry(name.to_string()).or_default();
        for t in tok {
            let v: u32 = t
                .parse()
                .map_err(|_| err(format!("'{t}' is not a vertex index")))?;
            if v as usize >= vertices {
                return Err(err(format!(
                    "vertex {v} is out of range (the mesh has {vertices} vertices)"
                )));
            }
            set.push(v);
        }
    }
    for v in out.values_mut() {
        v.sort_unstable();
        v.dedup();
    }
    Ok(out)
}

/// Reads a groups file for `mesh` and adds its groups (replacing same-named ones).
pub fn read_into(path: &Path, mesh: &mut Mesh) -> Result<(), FileError> {
    let name = path.display().to_string();
    let text = crate::files::read_text_limited(path, crate::files::MAX_TABLE_BYTES)?;
    mesh.groups
        .extend(parse(&name, &text, mesh.vertices.len())?);
    Ok(())
}

/// Serialises groups in the file form.
pub fn text(mesh: &Mesh) -> String {
    mesh.groups
        .iter()
        .map(|(k, v)| {
            format!(
                "{k} {}\n",
                v.iter().map(u32::to_string).collect::<Vec<_>>().join(" ")
            )
        })
        .collect()
}
