//! conformd's development set, for its tests and benchmarks only: outside meshes from
//! `tests/data/meshes` posed with known answers (`posing`), the standard and harder cases
//! in a development and a validation part (`devset`), the generic templates onto outside
//! animals and people scored by semantic landmarks (`semantic`), and one subject in many
//! postures for the repeatability bench (`repeat`). Kept out of the shipped library:
//! nothing the station runs reads `tests/data`.

pub mod devset;
pub mod posing;
pub mod repeat;
pub mod semantic;

/// Why a development case or subject could not be made.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error(transparent)]
    File(#[from] conformd::files::FileError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("no development mesh '{0}'")]
    NoMesh(String),
    #[error("{file}: {name} is not a vertex")]
    MarkNotVertex { file: String, name: String },
    #[error("{file} has no {name}")]
    NoMark { file: String, name: String },
    #[error("{subject}: mark {name} on vertex {vertex}, past the mesh")]
    MarkPastMesh {
        subject: String,
        name: String,
        vertex: u32,
    },
    #[error("{0}: no marks that say which way it faces")]
    NoFront(String),
    #[error("the generic template has no landmark '{0}'")]
    TemplateLandmark(String),
    #[error("the case has no truth")]
    NoTruth,
    #[error(transparent)]
    Template(#[from] conformd::template::TemplateError),
    #[error(transparent)]
    Rig(#[from] conformd::template::rig::RigCheckError),
    #[error(transparent)]
    StereoRig(#[from] conformd::stereo::rig::RigError),
    #[error(transparent)]
    Reconstruct(#[from] conformd::stereo::reconstruct::ReconstructError),
    #[error(transparent)]
    Scan(#[from] conformd::conform::correspond::ScanError),
    #[error("the posed subject's triangles: {0}")]
    Triangles(String),
    #[error("posing: {0}")]
    Posing(&'static str),
    #[error("the automatic rig found {arms} arms and {legs} legs, not two of each")]
    Limbs { arms: usize, legs: usize },
}
