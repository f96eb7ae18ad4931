//! The Embree side: the mesh and rays written for `bench/embree/embree_trace`, the program
//! run and its JSON read back, and the two tracers' hits compared.

use super::*;

/// Two tracers agree on a hit when their distances differ by at most this, relatively.
pub(crate) const T_TOLERANCE: f32 = 1e-4;

/// One result of the C++ program (its `Hit`): `prim` indexes the mesh written for it (the
/// domain's triangles in `Bvh::triangles` order).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(crate) struct EmbreeHit {
    pub(crate) t: f32,
    pub(crate) prim: u32,
}

pub(crate) const EMBREE_MISS: u32 = u32::MAX;

pub(crate) fn write_file(path: &Path, parts: &[&[u8]]) -> Result<()> {
    let mut f = BufWriter::new(File::create(path)?);
    for p in parts {
        f.write_all(p)?;
    }
    f.into_inner().map_err(|e| e.into_error())?;
    Ok(())
}

/// Writes the triangles for Embree as a mesh of three vertices each (the domain file keeps no
/// shared-vertex mesh; Embree copies vertices into its own leaves either way).
pub(crate) fn write_mesh(path: &Path, tris: &[PackedTriangle]) -> Result<()> {
    let v: Vec<[f32; 3]> = tris.iter().flat_map(|t| t.vertices()).collect();
    let i: Vec<[u32; 3]> = (0..tris.len() as u32)
        .map(|k| [3 * k, 3 * k + 1, 3 * k + 2])
        .collect();
    let counts = [v.len() as u64, i.len() as u64];
    write_file(
        path,
        &[
            bytemuck::bytes_of(&counts),
            bytemuck::cast_slice(&v),
            bytemuck::cast_slice(&i),
        ],
    )
}

pub(crate) fn write_rays(path: &Path, rays: &[BenchRay]) -> Result<()> {
    let count = rays.len() as u64;
    write_file(
        path,
        &[bytemuck::bytes_of(&count), bytemuck::cast_slice(rays)],
    )
}

/// How often the two tracers agree, and how they differ when they do not.
#[derive(Default)]
pub(crate) struct Agreement {
    pub(crate) rays: usize,
    /// Both miss, or both hit at distances within `T_TOLERANCE`.
    pub(crate) agree: usize,
    /// Both hit something.
    pub(crate) both_hit: usize,
    /// Both hit the same scene-wide triangle id.
    pub(crate) same_triangle: usize,
    pub(crate) only_rayfarm_hits: usize,
    pub(crate) only_embree_hits: usize,
    pub(crate) distance_differs: usize,
    /// A few disagreements for a person to look at: ray index, rayfarm, Embree.
    pub(crate) examples: Vec<String>,
}

impl Agreement {
    pub(crate) fn fraction(&self) -> f64 {
        self.agree as f64 / self.rays.max(1) as f64
    }
}

/// How far `ours` and `theirs` agree; for a shadow set (`any`) hit or miss is all there is.
pub(crate) fn compare(
    ours: &[Option<Hit>],
    theirs: &[EmbreeHit],
    mesh_ids: &[u64],
    any: bool,
) -> Agreement {
    let mut a = Agreement {
        rays: ours.len(),
        ..Default::default()
    };
    for (k, (o, e)) in ours.iter().zip(theirs).enumerate() {
        // Embree numbers triangles in mesh order; rayfarm reports scene-wide ids.
        let e = (e.prim != EMBREE_MISS).then(|| (e.t, mesh_ids[e.prim as usize]));
        let ok = match (o, e) {
            (None, None) => true,
            (Some(_), None) => {
                a.only_rayfarm_hits += 1;
                false
            }
            (None, Some(_)) => {
                a.only_embree_hits += 1;
                false
            }
            (Some(_), Some(_)) if any => {
                a.both_hit += 1;
                true
            }
            (Some(h), Some((t, id))) => {
                a.both_hit += 1;
                a.same_triangle += usize::from(h.id == id);
                let close = (h.t - t).abs() <= T_TOLERANCE * h.t.abs().max(t.abs());
                a.distance_differs += usize::from(!close);
                close
            }
        };
        a.agree += usize::from(ok);
        if !ok && a.examples.len() < 3 {
            let ours = o.map(|h| (h.t, h.id));
            a.examples
                .push(format!("ray {k}: rayfarm {ours:?}, embree {e:?}"));
        }
    }
    a
}

/// Runs the C++ program and returns its JSON line; its stderr passes through.
pub(crate) fn run_embree(opts: &Options, dir: &Path, sets: &[(&str, &Path)]) -> Result<Value> {
    let mut cmd = Command::new(&opts.embree);
    cmd.arg("--reps").arg(opts.reps.to_string());
    if opts.high {
        cmd.arg("--high");
    }
    cmd.arg(dir.join("mesh.bin")).arg(dir);
    for (name, path) in sets {
        cmd.arg(format!("{name}:{}", path.display()));
    }
    let out = cmd
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| format!("{}: {e}", opts.embree.display()))?;
    if !out.status.success() {
        return Err(format!("{} failed: {}", opts.embree.display(), out.status).into());
    }
    let stdout = String::from_utf8(out.stdout)?;
    let line = stdout
        .lines()
        .rfind(|l| l.starts_with('{'))
        .ok_or("embree_trace printed no JSON line")?;
    Ok(serde_json::from_str(line)?)
}

/// The Embree timing of set `name` in the build of `quality`, if that build ran.
pub(crate) fn embree_timing(report: &Value, quality: &str, name: &str) -> Option<Timing> {
    let build = report["builds"]
        .as_array()?
        .iter()
        .find(|b| b["quality"] == quality)?;
    let set = build["sets"]
        .as_array()?
        .iter()
        .find(|s| s["name"] == name)?;
    let seconds = set["seconds"].as_array()?.iter().map(Value::as_f64);
    Some(Timing(seconds.collect::<Option<Vec<f64>>>()?))
}
