//! Pinhole camera with Brown-Conrady distortion (OpenCV's k1, k2, p1, p2, k3).

use std::fmt;

use nalgebra::{Matrix2, Matrix3, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::quat_from_wxyz;

/// Image position `(u, v)` = (column, row) in pixels; `(0, 0)` is the centre
/// of the top-left pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pixel {
    pub u: f64,
    pub v: f64,
}

impl Pixel {
    pub fn new(u: f64, v: f64) -> Self {
        Self { u, v }
    }

    pub fn distance_px(&self, other: &Pixel) -> f64 {
        (self.u - other.u).hypot(self.v - other.v)
    }
}

/// A point on the normalized image plane z = 1 of the camera frame:
/// `(x/z, y/z)`, either undistorted (ideal pinhole) or distorted (after the
/// lens model, before the intrinsics), as each function says.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NormalizedPoint {
    pub x: f64,
    pub y: f64,
}

impl NormalizedPoint {
    pub fn new(x: f64, y: f64) -> Self {
        Self { x, y }
    }

    /// The camera-frame direction `(x, y, 1)` (not normalized).
    pub fn to_direction(&self) -> Vector3<f64> {
        Vector3::new(self.x, self.y, 1.0)
    }
}

/// Brown-Conrady lens distortion in OpenCV's order and formula: radial
/// `k1, k2, k3` and tangential `p1, p2` on normalized coordinates.
/// Coefficients missing from JSON are zero.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub p1: f64,
    #[serde(default)]
    pub p2: f64,
    #[serde(default)]
    pub k3: f64,
}

impl Distortion {
    pub fn is_zero(&self) -> bool {
        [self.k1, self.k2, self.p1, self.p2, self.k3].iter().all(|&c| c == 0.0)
    }

    /// Undistorted -> distorted normalized coordinates:
    /// `x'' = x'(1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x'y' + p2 (r2 + 2x'^2)`,
    /// `y'' = y'(1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2y'^2) + 2 p2 x'y'`.
    pub fn apply(&self, p: NormalizedPoint) -> NormalizedPoint {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        NormalizedPoint {
            x: x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y: y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        }
    }

    /// Jacobian of [`Distortion::apply`] with respect to `(x', y')`.
    pub fn jacobian(&self, p: NormalizedPoint) -> Matrix2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r2)
        let d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let cross = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        Matrix2::new(
            radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
            cross,
            cross,
            radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x,
        )
    }

    /// Distorted -> undistorted normalized coordinates: Newton's method on
    /// [`Distortion::apply`], started at the distorted point and damped so the
    /// residual never grows. Converges to ~1e-15 within a few iterations over
    /// the whole image of realistic lenses (where the model is invertible);
    /// elsewhere it returns the best point found.
    pub fn invert(&self, distorted: NormalizedPoint) -> NormalizedPoint {
        if self.is_zero() {
            return distorted;
        }
        let target = Vector2::new(distorted.x, distorted.y);
        let residual = |p: NormalizedPoint| {
            let d = self.apply(p);
            target - Vector2::new(d.x, d.y)
        };
        let mut p = distorted;
        let mut r = residual(p);
        for _ in 0..MAX_NEWTON_ITERATIONS {
            if r.norm() <= NEWTON_TOLERANCE * (1.0 + target.norm()) {
                break;
            }
            let Some(step) = self.jacobian(p).lu().solve(&r) else { break };
            // Halve the step until the residual decreases (at most a few times).
            let mut scale = 1.0;
            let mut improved = false;
            for _ in 0..30 {
                let q = NormalizedPoint::new(p.x + scale * step.x, p.y + scale * step.y);
                let rq = residual(q);
                if rq.norm() < r.norm() {
                    (p, r, improved) = (q, rq, true);
                    break;
                }
                scale *= 0.5;
            }
            if !improved {
                break;
            }
        }
        p
    }
}

/// Newton stops once the residual is below this (relative to 1 + |distorted|).
const NEWTON_TOLERANCE: f64 = 1e-15;
const MAX_NEWTON_ITERATIONS: usize = 50;

/// Intrinsics of a pinhole camera with lens distortion (the camera model of
/// the flight format's `camera.json`, without the mounting).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    /// Image size in pixels.
    pub width: u32,
    pub height: u32,
    /// Focal lengths in pixels (`u = fx x'' + cx`, `v = fy y'' + cy`).
    pub fx: f64,
    pub fy: f64,
    /// Principal point in pixels ((0, 0) = centre of the top-left pixel).
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub distortion: Distortion,
}

/// Why a [`CameraModel`] cannot be used.
#[derive(Clone, Debug, PartialEq)]
pub struct InvalidCamera(pub String);

impl fmt::Display for InvalidCamera {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "invalid camera model: {}", self.0)
    }
}

impl std::error::Error for InvalidCamera {}

impl CameraModel {
    /// Distortion-free camera with square pixels, the principal point at the
    /// image centre `((w-1)/2, (h-1)/2)` and a horizontal field of view of
    /// `hfov_deg` from the left edge of the image to the right edge.
    pub fn from_fov(width: u32, height: u32, hfov_deg: f64) -> Self {
        let f_px = 0.5 * width as f64 / (0.5 * hfov_deg.to_radians()).tan();
        Self {
            width,
            height,
            fx: f_px,
            fy: f_px,
            cx: 0.5 * (width as f64 - 1.0),
            cy: 0.5 * (height as f64 - 1.0),
            distortion: Distortion::default(),
        }
    }

    /// Angle (degrees) between the rays through the middles of the left and
    /// right image edges (through the principal point's row).
    pub fn hfov_deg(&self) -> f64 {
        let left = self.ray(Pixel::new(-0.5, self.cy));
        let right = self.ray(Pixel::new(self.width as f64 - 0.5, self.cy));
        angle_deg(&left, &right)
    }

    /// Angle (degrees) between the rays through the middles of the top and
    /// bottom image edges (through the principal point's column).
    pub fn vfov_deg(&self) -> f64 {
        let top = self.ray(Pixel::new(self.cx, -0.5));
        let bottom = self.ray(Pixel::new(self.cx, self.height as f64 - 0.5));
        angle_deg(&top, &bottom)
    }

    /// The intrinsic matrix `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    pub fn principal_point(&self) -> Pixel {
        Pixel::new(self.cx, self.cy)
    }

    /// Checks sizes and focal lengths, and that the lens model can be inverted
    /// over the whole image (no fold-over of the distortion polynomial).
    pub fn validate(&self) -> Result<(), InvalidCamera> {
        if self.width == 0 || self.height == 0 {
            return Err(InvalidCamera(format!("image size {}x{}", self.width, self.height)));
        }
        if !(self.fx > 0.0 && self.fy > 0.0 && self.fx.is_finite() && self.fy.is_finite()) {
            return Err(InvalidCamera(format!("focal lengths fx={} fy={}", self.fx, self.fy)));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(InvalidCamera(format!("principal point ({}, {})", self.cx, self.cy)));
        }
        let d = self.distortion;
        if ![d.k1, d.k2, d.p1, d.p2, d.k3].iter().all(|c| c.is_finite()) {
            return Err(InvalidCamera(format!("distortion {d:?}")));
        }
        // Fold-over shows first along the image border: walk it.
        let (w, h) = (self.width as f64 - 0.5, self.height as f64 - 0.5);
        const STEPS: usize = 64;
        for i in 0..=STEPS {
            let s = i as f64 / STEPS as f64;
            for px in [
                Pixel::new(-0.5 + s * (w + 0.5), -0.5),
                Pixel::new(-0.5 + s * (w + 0.5), h),
                Pixel::new(-0.5, -0.5 + s * (h + 0.5)),
                Pixel::new(w, -0.5 + s * (h + 0.5)),
            ] {
                let n = self.pixel_to_normalized(px);
                let back = self.normalized_to_pixel(n);
                let det = self.distortion.jacobian(n).determinant();
                if !(back.distance_px(&px) < 1e-6 && det > 0.0) {
                    return Err(InvalidCamera(format!(
                        "distortion {d:?} cannot be inverted at pixel ({}, {})",
                        px.u, px.v
                    )));
                }
            }
        }
        Ok(())
    }

    /// Pixel of a camera-frame point, `None` when it is not in front of the
    /// camera (`z <= 0`). The pixel may lie outside the image; far outside the
    /// field of view a distortion polynomial can fold back, see
    /// [`CameraModel::project_in_image`].
    pub fn project(&self, p_cam: &Vector3<f64>) -> Option<Pixel> {
        if p_cam.z.is_nan() || p_cam.z <= 0.0 {
            return None;
        }
        Some(self.normalized_to_pixel(NormalizedPoint::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z)))
    }

    /// Like [`CameraModel::project`], but `None` unless the pixel is inside the
    /// image *and* is the lens model's genuine image of the point (not a
    /// fold-back of a point far outside the field of view).
    pub fn project_in_image(&self, p_cam: &Vector3<f64>) -> Option<Pixel> {
        let px = self.project(p_cam)?;
        if !self.contains(px) {
            return None;
        }
        if !self.distortion.is_zero() {
            let n = NormalizedPoint::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z);
            let back = self.pixel_to_normalized(px);
            if (back.x - n.x).hypot(back.y - n.y) > 1e-9 * (1.0 + n.x.hypot(n.y)) {
                return None;
            }
        }
        Some(px)
    }

    /// Undistorted -> distorted normalized coordinates (the lens model).
    pub fn distort(&self, undistorted: NormalizedPoint) -> NormalizedPoint {
        self.distortion.apply(undistorted)
    }

    /// Distorted -> undistorted normalized coordinates (iterative inverse of
    /// [`CameraModel::distort`], see [`Distortion::invert`]).
    pub fn undistort(&self, distorted: NormalizedPoint) -> NormalizedPoint {
        self.distortion.invert(distorted)
    }

    /// Pixel of an undistorted normalized point (distortion, then intrinsics).
    pub fn normalized_to_pixel(&self, undistorted: NormalizedPoint) -> Pixel {
        self.distorted_to_pixel(self.distort(undistorted))
    }

    /// Undistorted normalized point of a pixel (intrinsics inverse, then undistortion).
    pub fn pixel_to_normalized(&self, px: Pixel) -> NormalizedPoint {
        self.undistort(self.pixel_to_distorted(px))
    }

    /// Intrinsics only: distorted normalized point -> pixel.
    pub fn distorted_to_pixel(&self, distorted: NormalizedPoint) -> Pixel {
        Pixel::new(self.fx * distorted.x + self.cx, self.fy * distorted.y + self.cy)
    }

    /// Intrinsics inverse only: pixel -> distorted normalized point.
    pub fn pixel_to_distorted(&self, px: Pixel) -> NormalizedPoint {
        NormalizedPoint::new((px.u - self.cx) / self.fx, (px.v - self.cy) / self.fy)
    }

    /// Unit camera-frame direction of the ray through a pixel (undistorted).
    pub fn ray(&self, px: Pixel) -> Vector3<f64> {
        self.pixel_to_normalized(px).to_direction().normalize()
    }

    /// True when the pixel lies on the image: `[-0.5, w - 0.5] x [-0.5, h - 0.5]`
    /// (the outer edges of the border pixels included).
    pub fn contains(&self, px: Pixel) -> bool {
        (-0.5..=self.width as f64 - 0.5).contains(&px.u) && (-0.5..=self.height as f64 - 0.5).contains(&px.v)
    }

    /// Centres of the four corner pixels: top-left, top-right, bottom-right, bottom-left.
    pub fn corners(&self) -> [Pixel; 4] {
        let (r, b) = (self.width as f64 - 1.0, self.height as f64 - 1.0);
        [Pixel::new(0.0, 0.0), Pixel::new(r, 0.0), Pixel::new(r, b), Pixel::new(0.0, b)]
    }
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    // atan2 keeps full precision for small and near-180-degree angles alike.
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

/// The flight format's `camera.json`: the camera model's fields at the top
/// level, plus the mounting `q_cam_imu` (`[w, x, y, z]`, rotates IMU-frame
/// vectors into the camera frame: `v_cam = R(q_cam_imu) * v_imu`; identity
/// when absent).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraConfig {
    #[serde(flatten)]
    pub model: CameraModel,
    #[serde(default = "identity_wxyz")]
    pub q_cam_imu: [f64; 4],
}

fn identity_wxyz() -> [f64; 4] {
    [1.0, 0.0, 0.0, 0.0]
}

impl CameraConfig {
    /// The mounting rotation as a unit quaternion (`v_cam = q * v_imu`).
    pub fn q_cam_imu(&self) -> UnitQuaternion<f64> {
        quat_from_wxyz(self.q_cam_imu)
    }
}
