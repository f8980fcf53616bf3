//! A planar rectangle of the world ([`PlanarQuad`]): the surface the scene's rooms and
//! walls are made of ([`crate::scene`]) and that the textures cover ([`crate::texture`]).
//! World frame (x right, y down, z forward), metres. Pitfall: the edge directions must be
//! unit and perpendicular; the normal of the visible side is their cross product.

use nalgebra::{Point3, Vector3};

/// A planar rectangle in the world frame: `corner + a * u + b * v` for `a` in
/// `[0, |u|]`, `b` in `[0, |v|]` (metres, `u` and `v` unit and perpendicular). `u x v` is
/// the normal of the **visible** side (into the room for walls, outward for boxes): a
/// surface seen from its back is never the first hit in a closed room.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarQuad {
    /// The first corner, world frame.
    pub corner: Point3<f64>,
    /// Unit direction of the first edge, world frame.
    pub u: Vector3<f64>,
    /// Unit direction of the second edge, world frame.
    pub v: Vector3<f64>,
    /// Lengths of the two edges, metres.
    pub size_m: [f64; 2],
}

impl PlanarQuad {
    /// The rectangle centred at `centre` with half edges `half_u`, `half_v` (vectors,
    /// perpendicular; their cross product is the visible side's normal).
    pub(crate) fn centred(centre: Point3<f64>, half_u: Vector3<f64>, half_v: Vector3<f64>) -> Self {
        let (lu, lv) = (half_u.norm(), half_v.norm());
        Self {
            corner: centre - half_u - half_v,
            u: half_u / lu,
            v: half_v / lv,
            size_m: [2.0 * lu, 2.0 * lv],
        }
    }

    /// Unit normal of the visible side, `u x v`.
    pub fn normal(&self) -> Vector3<f64> {
        self.u.cross(&self.v)
    }

    /// The four corners in order `corner`, `+u`, `+u+v`, `+v`, world frame.
    pub fn corners(&self) -> [Point3<f64>; 4] {
        let (du, dv) = (self.u * self.size_m[0], self.v * self.size_m[1]);
        [self.corner, self.corner + du, self.corner + du + dv, self.corner + dv]
    }
}
