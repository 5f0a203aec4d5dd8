//! Landmark files: text lines `name vertex_index` (on a template) or `name x y z` (on a
//! scan), `#` comments; and MeshLab picked-points `.pp` files. Landmarks pair up by name.

use super::V3;
use crate::files::FileError;
use std::path::Path;

/// Where a landmark sits: a vertex of the mesh it belongs to, or a free point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LandmarkPos {
    Vertex(u32),
    Point(V3),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Landmark {
    pub name: String,
    pub pos: LandmarkPos,
}

/// Largest landmark file read: thousands of named points, not a mesh.
pub const MAX_LANDMARK_BYTES: u64 = 16 << 20;

/// Reads a landmark file; `.pp` files are read as MeshLab picked points, anything else as
/// text.
pub fn read_landmarks(path: &Path) -> Result<Vec<Landmark>, FileError> {
    let name = path.display().to_string();
    let bytes = crate::files::read_limited(path, MAX_LANDMARK_BYTES)?;
    let is_pp = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("pp"));
    if is_pp {
        parse_pp(&name, &bytes)
    } else {
        parse_text(&name, &bytes)
    }
}

/// Parses the text form; every name must be unique.
pub fn parse_text(path: &str, bytes: &[u8]) -> Result<Vec<Landmark>, FileError> {
    let text =
        std::str::from_utf8(bytes).map_err(|_| FileError::content(path, "not a text file"))?;
    let mut out: Vec<Landmark> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let err = |msg: String| FileError::line(path, i + 1, msg);
        let tok: Vec<&str> = line.split_whitespace().collect();
        let pos = match tok.len() {
            2 => LandmarkPos::Vertex(
                tok[1]
                    .parse()
                    .map_err(|_| err(format!("'{}' is not a vertex index", tok[1])))?,
            ),
            4 => {
                let c: Vec<f64> = tok[1..]
                    .iter()
                    .map(|t| {
                        t.parse::<f64>()
                            .map_err(|_| err(format!("'{t}' is not a number")))
                    })
                    .collect::<Result<_, _>>()?;
                if !c.iter().all(|x| x.is_finite()) {
                    return Err(err(format!(
                        "landmark '{}' has a non-finite coordinate",
                        tok[0]
                    )));
                }
                LandmarkPos::Point(V3::new(c[0], c[1], c[2]))
            }
            n => {
                return Err(err(format!(
                    "expected 'name index' or 'name x y z', found {n} fields"
                )));
            }
        };
        push_unique(&mut out, tok[0], pos).map_err(|e| err(e.to_string()))?;
    }
    Ok(out)
}

/// A landmark that cannot be used as given.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LandmarkError {
    #[error("landmark '{0}' appears twice")]
    Twice(String),
    #[error(
        "scan landmark '{name}' is given as vertex index {vertex}; a scan's landmarks are points, one 'name x y z' line each (vertex indices belong in a template's landmark file)"
    )]
    ScanVertex { name: String, vertex: u32 },
}

fn push_unique(out: &mut Vec<Landmark>, name: &str, pos: LandmarkPos) -> Result<(), LandmarkError> {
    if out.iter().any(|l| l.name == name) {
        return Err(LandmarkError::Twice(name.to_string()));
    }
    out.push(Landmark {
        name: name.to_string(),
        pos,
    });
    Ok(())
}

/// Parses a MeshLab `.pp` file: `<point x=".." y=".." z=".." name=".." active="1"/>`.
/// Inactive points are skipped.
pub fn parse_pp(path: &str, bytes: &[u8]) -> Result<Vec<Landmark>, FileError> {
    let text =
        std::str::from_utf8(bytes).map_err(|_| FileError::content(path, "not a text file"))?;
    if !text.contains("PickedPoints") {
        return Err(FileError::content(path, "not a MeshLab PickedPoints file"));
    }
    let mut out = Vec::new();
    let mut rest = text;
    let mut offset = 0;
    while let Some(start) = rest.find("<point") {
        let line = text[..offset + start].lines().count().max(1);
        let err = |msg: String| FileError::line(path, line, msg);
        let tail = &rest[start..];
        let end = tail
            .find('>')
            .ok_or_else(|| err("unterminated <point> tag".into()))?;
        let tag = &tail[..end];
        let attr = |k: &str| -> Option<&str> {
            let pat = format!(" {k}=\"");
            let i = tag.find(&pat)? + pat.len();
            tag[i..].find('"').map(|j| &tag[i..i + j])
        };
        if attr("active") != Some("0") {
            let mut c = [0.0; 3];
            for (k, n) in ["x", "y", "z"].iter().enumerate() {
                let s = attr(n).ok_or_else(|| err(format!("<point> without {n}")))?;
                c[k] = s
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite())
                    .ok_or_else(|| err(format!("{n}=\"{s}\" is not a finite number")))?;
            }
            let name = attr("name")
                .map(str::to_string)
                .unwrap_or_else(|| format!("p{}", out.len()));
            push_unique(
                &mut out,
                &name,
                LandmarkPos::Point(V3::new(c[0], c[1], c[2])),
            )
            .map_err(|e| err(e.to_string()))?;
        }
        offset += start + end;
        rest = &text[offset..];
    }
    Ok(out)
}

/// Serialises landmarks in the text form.
pub fn landmarks_text(lms: &[Landmark]) -> String {
    lms.iter()
        .map(|l| match l.pos {
            LandmarkPos::Vertex(i) => format!("{} {}\n", l.name, i),
            LandmarkPos::Point(p) => format!("{} {} {} {}\n", l.name, p.x, p.y, p.z),
        })
        .collect()
}

/// Scan landmarks as points. A landmark given as a vertex index is refused: a scan's
/// points come in no fixed order (a reconstruction numbers them anew each time), so an
/// index from a template's landmark file, used on a scan, names an arbitrary point.
pub fn scan_points(lms: &[Landmark]) -> Result<Vec<(String, V3)>, LandmarkError> {
    lms.iter()
        .map(|l| match l.pos {
            LandmarkPos::Point(p) => Ok((l.name.clone(), p)),
            LandmarkPos::Vertex(vertex) => Err(LandmarkError::ScanVertex {
                name: l.name.clone(),
                vertex,
            }),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_and_pp_forms() {
        let t = parse_text("a.txt", b"# comment\nsnout 12\nnose 0.5 1 -2\n").unwrap();
        assert_eq!(t[0].pos, LandmarkPos::Vertex(12));
        assert_eq!(t[1].pos, LandmarkPos::Point(V3::new(0.5, 1.0, -2.0)));
        let pp = br#"<!DOCTYPE PickedPoints><PickedPoints>
 <point x="1" y="2" z="3" name="tail" active="1"/>
 <point x="1" y="2" z="3" name="off" active="0"/>
</PickedPoints>"#;
        let p = parse_pp("a.pp", pp).unwrap();
        assert_eq!(p.len(), 1);
        assert_eq!(p[0].name, "tail");
    }

    #[test]
    fn bad_lines_are_named() {
        let e = parse_text("a.txt", b"a 1\nb x y z\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("line 2") && e.contains("'x' is not a number"),
            "{e}"
        );
        let e = parse_text("a.txt", b"a 1\na 2\n").unwrap_err().to_string();
        assert!(e.contains("appears twice"), "{e}");
        let e = parse_text("a.txt", b"a nan 0 0\n").unwrap_err().to_string();
        assert!(e.contains("non-finite"), "{e}");
    }
}
