//! TEMPORARY minimal stand-in, replaced by the full module on merge.
use nalgebra::Matrix4;
/// Y ~ H X.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Homography3(pub Matrix4<f64>);
impl Homography3 {
    /// Determinant +1, trace positive.
    pub fn normalized_det(&self) -> crate::Result<Self> {
        let det = self.0.determinant();
        if !(det > 0.0) {
            return Err(crate::GeometryError::InvalidEstimate("not conjugate to a rigid motion".into()));
        }
        let mut h = self.0 / det.powf(0.25);
        if h.trace() < 0.0 {
            h = -h;
        }
        Ok(Self(h))
    }
}
