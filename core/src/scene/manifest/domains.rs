//! Opening a domain's files, from storage or as bytes a peer sent, and checking them against
//! the manifest's entry for the domain: the one way every reader gets a domain.

use std::path::{Path, PathBuf};

use super::{DomainEntry, Manifest};
use crate::scene::{DomainData, MANIFEST_FILE, Received, Residence, SceneError};

impl Manifest {
    /// Maps domain `domain` of the scene in `dir` and checks it against this manifest: its id,
    /// its size, its header checksum, its materials; with `verify_checksum` also hashes every
    /// byte. The one way every reader opens a domain.
    pub fn open_domain(
        &self,
        dir: &Path,
        domain: u32,
        verify_checksum: bool,
    ) -> Result<DomainData, SceneError> {
        self.open_domain_as(dir, domain, verify_checksum, None)
    }

    /// [`Manifest::open_domain`], its files held in memory as `residence` says (`None`: as the
    /// process chooses, [`Residence::selected`]).
    pub fn open_domain_as(
        &self,
        dir: &Path,
        domain: u32,
        verify_checksum: bool,
        residence: Option<Residence>,
    ) -> Result<DomainData, SceneError> {
        let entry = self
            .domains
            .get(domain as usize)
            .ok_or_else(|| SceneError::Manifest {
                path: dir.join(MANIFEST_FILE),
                reason: format!("no domain {domain} of {}", self.domains.len()),
            })?;
        let checksum = checksum_value(&entry.checksum);
        let path = dir.join(&entry.file);
        let materials = self.materials.len() as u32;
        let mut data = DomainData::open_as(&path, checksum, verify_checksum, materials, residence)?;
        if let Some(s) = &entry.surfaces {
            let checksum = checksum_value(&s.checksum);
            let file = dir.join(&s.file);
            let surfaces =
                DomainData::open_as(&file, checksum, verify_checksum, materials, residence)?;
            data.attach_surfaces(surfaces)?;
        }
        self.check_domain(entry, domain, path, data)
    }

    /// The domain `domain` from bytes that arrived from a peer (`origin` names it in errors):
    /// its file and, for a brick with surfaces, its surfaces' file, each checked against its
    /// own checksum in the manifest, then against the manifest's entry exactly as
    /// [`Manifest::open_domain`] checks a file from storage. Nothing here trusts the sender.
    pub fn received_domain(
        &self,
        origin: &Path,
        domain: u32,
        file: Received,
        surfaces: Option<Received>,
    ) -> Result<DomainData, SceneError> {
        let entry = self
            .domains
            .get(domain as usize)
            .ok_or_else(|| SceneError::Domain {
                path: origin.into(),
                reason: format!("no domain {domain} of {}", self.domains.len()),
            })?;
        let materials = self.materials.len() as u32;
        let checksum = checksum_value(&entry.checksum);
        let mut data = DomainData::from_received(file, origin, checksum, materials)?;
        match (&entry.surfaces, surfaces) {
            (Some(s), Some(received)) => {
                let checksum = checksum_value(&s.checksum);
                let surfaces = DomainData::from_received(received, origin, checksum, materials)?;
                data.attach_surfaces(surfaces)?;
            }
            (None, None) => {}
            (expected, _) => {
                return Err(SceneError::Domain {
                    path: origin.into(),
                    reason: format!(
                        "sent {} surfaces file where the manifest has {}",
                        if expected.is_some() { "no" } else { "a" },
                        if expected.is_some() { "one" } else { "none" }
                    ),
                });
            }
        }
        self.check_domain(entry, domain, origin.into(), data)
    }

    /// `data` if it is what the manifest's `entry` for `domain` describes.
    fn check_domain(
        &self,
        entry: &DomainEntry,
        domain: u32,
        path: PathBuf,
        data: DomainData,
    ) -> Result<DomainData, SceneError> {
        let mismatch = if data.domain() != domain {
            Some(format!(
                "holds domain {}, the manifest says {domain}",
                data.domain()
            ))
        } else if data.bytes() != entry.bytes {
            Some(format!(
                "is {} bytes, the manifest says {}",
                data.bytes(),
                entry.bytes
            ))
        } else if data.brick().is_some() != self.volume.is_some() {
            Some(match self.volume {
                Some(_) => "is a mesh domain in a volume scene".to_string(),
                None => "is a volume brick in a scene of triangles".to_string(),
            })
        } else if let (Some(b), Some(v)) = (data.brick(), &self.volume)
            && (b.header.volume_dims != v.dims
                || entry.values != Some([b.header.value_min, b.header.value_max]))
        {
            Some("brick's volume dims or value range differ from the manifest's".to_string())
        } else if data.triangle_count() != entry.triangles {
            Some(format!(
                "holds {} triangles, the manifest says {}",
                data.triangle_count(),
                entry.triangles
            ))
        } else {
            None
        };
        match mismatch {
            Some(reason) => Err(SceneError::Domain { path, reason }),
            None => Ok(data),
        }
    }

    /// Maps every domain file once to check it matches this build and the manifest; with
    /// `verify_checksums` also hashes every byte.
    pub fn check_domains(&self, dir: &Path, verify_checksums: bool) -> Result<(), SceneError> {
        for d in 0..self.domains.len() as u32 {
            // Mapped: the check keeps nothing, so a copy into huge pages would be wasted.
            self.open_domain_as(dir, d, verify_checksums, Some(Residence::Mapped))?;
        }
        Ok(())
    }
}

/// A checksum of the domain table as a number (its hex was checked when the manifest was
/// read).
fn checksum_value(hex: &str) -> u64 {
    u64::from_str_radix(hex, 16).unwrap_or_default()
}
