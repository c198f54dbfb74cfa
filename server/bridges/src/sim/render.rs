//! A small software ray caster for the simulated scene: table, basket, ball and the SO-101 links as
//! capsules, seen from a fixed pinhole camera, written as packed RGB8.
//!
//! The static part (table and basket: colour, depth and material per pixel) is ray cast once per image size
//! and cached. Each frame copies it and then ray casts only the dynamic primitives inside their projected
//! bounding boxes, with a depth test against the cache, so a frame costs a memcpy plus a few thousand ray
//! intersections per link. Shadows are straight-down projections onto the table, enough for a policy (or a
//! person) to judge height above the table.

use super::config::SimCameraConfig;
use super::world::{
    BASKET_FLOOR_M, FINGER_HALF_THICKNESS_M, FINGER_HALF_WIDTH_M, FINGER_ROOT_M, FINGER_TIP_M, SceneSnapshot,
    half_gap_m,
};
use nalgebra::Vector3;
use small::{V2, V3};

/// Minimal f32 vectors for the per-pixel loops: nalgebra's generic code is fine optimised but about a
/// hundred times slower unoptimised, and the server is often run as a debug build during development.
mod small {
    use std::ops::{Add, Mul, Sub};

    #[derive(Clone, Copy, Debug, PartialEq)]
    pub struct V3 {
        pub x: f32,
        pub y: f32,
        pub z: f32,
    }

    #[derive(Clone, Copy, Debug, PartialEq)]
    pub struct V2 {
        pub x: f32,
        pub y: f32,
    }

    impl V3 {
        pub const fn new(x: f32, y: f32, z: f32) -> Self {
            Self { x, y, z }
        }
        pub const fn x() -> Self {
            Self::new(1.0, 0.0, 0.0)
        }
        pub const fn z() -> Self {
            Self::new(0.0, 0.0, 1.0)
        }
        pub fn from_f64(v: &nalgebra::Vector3<f64>) -> Self {
            Self::new(v.x as f32, v.y as f32, v.z as f32)
        }
        #[inline]
        pub fn dot(&self, o: &Self) -> f32 {
            self.x * o.x + self.y * o.y + self.z * o.z
        }
        pub fn cross(&self, o: &Self) -> Self {
            Self::new(
                self.y * o.z - self.z * o.y,
                self.z * o.x - self.x * o.z,
                self.x * o.y - self.y * o.x,
            )
        }
        #[inline]
        pub fn norm_squared(&self) -> f32 {
            self.dot(self)
        }
        pub fn normalize(&self) -> Self {
            *self * (1.0 / self.norm_squared().sqrt())
        }
        pub fn try_normalize(&self, eps: f32) -> Option<Self> {
            let n = self.norm_squared().sqrt();
            (n > eps).then(|| *self * (1.0 / n))
        }
        #[inline]
        pub fn xy(&self) -> V2 {
            V2 { x: self.x, y: self.y }
        }
    }

    impl From<[f32; 3]> for V3 {
        fn from(v: [f32; 3]) -> Self {
            Self::new(v[0], v[1], v[2])
        }
    }

    impl Add for V3 {
        type Output = Self;
        #[inline]
        fn add(self, o: Self) -> Self {
            Self::new(self.x + o.x, self.y + o.y, self.z + o.z)
        }
    }

    impl Sub for V3 {
        type Output = Self;
        #[inline]
        fn sub(self, o: Self) -> Self {
            Self::new(self.x - o.x, self.y - o.y, self.z - o.z)
        }
    }

    impl Mul<f32> for V3 {
        type Output = Self;
        #[inline]
        fn mul(self, k: f32) -> Self {
            Self::new(self.x * k, self.y * k, self.z * k)
        }
    }

    /// Reference forms, so call sites can mix `&V3` and `V3` like nalgebra allows.
    macro_rules! by_ref {
        ($t:ty) => {
            impl Sub<&$t> for &$t {
                type Output = $t;
                #[inline]
                fn sub(self, o: &$t) -> $t {
                    *self - *o
                }
            }
            impl Sub<$t> for &$t {
                type Output = $t;
                #[inline]
                fn sub(self, o: $t) -> $t {
                    *self - o
                }
            }
            impl Sub<&$t> for $t {
                type Output = $t;
                #[inline]
                fn sub(self, o: &$t) -> $t {
                    self - *o
                }
            }
            impl Mul<f32> for &$t {
                type Output = $t;
                #[inline]
                fn mul(self, k: f32) -> $t {
                    *self * k
                }
            }
        };
    }
    by_ref!(V3);
    by_ref!(V2);

    impl Add<&V3> for V3 {
        type Output = Self;
        #[inline]
        fn add(self, o: &Self) -> Self {
            self + *o
        }
    }

    impl V2 {
        pub const fn new(x: f32, y: f32) -> Self {
            Self { x, y }
        }
        #[inline]
        pub fn dot(self, o: Self) -> f32 {
            self.x * o.x + self.y * o.y
        }
        #[inline]
        pub fn norm_squared(self) -> f32 {
            self.dot(self)
        }
    }

    impl Sub for V2 {
        type Output = Self;
        #[inline]
        fn sub(self, o: Self) -> Self {
            Self::new(self.x - o.x, self.y - o.y)
        }
    }

    impl Mul<f32> for V2 {
        type Output = Self;
        #[inline]
        fn mul(self, k: f32) -> Self {
            Self::new(self.x * k, self.y * k)
        }
    }
}

const LIGHT: [f32; 3] = [0.35, -0.45, 0.82];
const AMBIENT: f32 = 0.38;
const TABLE_X_M: (f32, f32) = (-0.12, 0.52);
const TABLE_Y_M: (f32, f32) = (-0.36, 0.36);

const SKY_TOP: [f32; 3] = [176.0, 188.0, 204.0];
const SKY_BOTTOM: [f32; 3] = [112.0, 120.0, 138.0];
const TABLE: [f32; 3] = [206.0, 178.0, 138.0];
const TABLE_LINE: [f32; 3] = [176.0, 148.0, 110.0];
const BASKET_OUT: [f32; 3] = [60.0, 100.0, 196.0];
const BASKET_IN: [f32; 3] = [40.0, 70.0, 150.0];
const BASKET_RIM: [f32; 3] = [225.0, 230.0, 240.0];
const LINK: [f32; 3] = [240.0, 172.0, 36.0];
const JOINT: [f32; 3] = [58.0, 58.0, 64.0];
const FINGER: [f32; 3] = [84.0, 84.0, 92.0];
const BALL: [f32; 3] = [214.0, 38.0, 38.0];

/// What a background pixel shows; shadows fall only on horizontal surfaces.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Material {
    Sky,
    Table,
    BasketWall,
    BasketFloor,
}

/// A pinhole camera with z up.
#[derive(Clone, Debug)]
struct Camera {
    eye: V3,
    forward: V3,
    right: V3,
    up: V3,
    tan_half_fov: f32,
}

impl Camera {
    fn new(config: &SimCameraConfig) -> Self {
        let eye = V3::from(config.eye_m.map(|v| v as f32));
        let look_at = V3::from(config.look_at_m.map(|v| v as f32));
        let forward = (look_at - eye).normalize();
        // Looking straight down would make "right" undefined; any horizontal axis will do then.
        let right = forward.cross(&V3::z()).try_normalize(1e-6).unwrap_or_else(V3::x);
        let up = right.cross(&forward);
        let tan_half_fov = (config.vertical_fov_deg.to_radians() as f32 * 0.5).tan();
        Self {
            eye,
            forward,
            right,
            up,
            tan_half_fov,
        }
    }
}

/// Per-size projection constants.
#[derive(Clone, Copy)]
struct Projection {
    width: usize,
    height: usize,
    focal_px: f32,
    cx: f32,
    cy: f32,
}

impl Projection {
    fn new(camera: &Camera, width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            focal_px: height as f32 * 0.5 / camera.tan_half_fov,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
        }
    }

    /// Unit ray direction through the centre of pixel (x, y).
    #[inline]
    fn ray(&self, camera: &Camera, x: usize, y: usize) -> V3 {
        let u = (x as f32 + 0.5 - self.cx) / self.focal_px;
        let v = (self.cy - (y as f32 + 0.5)) / self.focal_px;
        (camera.forward + camera.right * u + camera.up * v).normalize()
    }

    /// Pixel coordinates and camera depth of a point; `None` behind the camera.
    fn project(&self, camera: &Camera, p: &V3) -> Option<(f32, f32, f32)> {
        let d = p - camera.eye;
        let z = d.dot(&camera.forward);
        if z < 1e-3 {
            return None;
        }
        Some((
            self.cx + self.focal_px * d.dot(&camera.right) / z,
            self.cy - self.focal_px * d.dot(&camera.up) / z,
            z,
        ))
    }

    /// Pixel bounding box `(x0, x1, y0, y1)` (exclusive ends) of points grown by a world radius; `None` if it
    /// is empty or a point is behind the camera.
    fn bbox(&self, camera: &Camera, points: &[V3], radius: f32) -> Option<(usize, usize, usize, usize)> {
        let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for p in points {
            let (x, y, z) = self.project(camera, p)?;
            let r = self.focal_px * radius / z + 2.0;
            x0 = x0.min(x - r);
            x1 = x1.max(x + r);
            y0 = y0.min(y - r);
            y1 = y1.max(y + r);
        }
        let clamp_x = |v: f32| v.clamp(0.0, self.width as f32) as usize;
        let clamp_y = |v: f32| v.clamp(0.0, self.height as f32) as usize;
        let (x0, x1, y0, y1) = (clamp_x(x0), clamp_x(x1.ceil()), clamp_y(y0), clamp_y(y1.ceil()));
        (x0 < x1 && y0 < y1).then_some((x0, x1, y0, y1))
    }
}

/// The cached static image for one size.
struct Background {
    width: usize,
    height: usize,
    key: [u64; 4],
    rgb: Vec<u8>,
    depth: Vec<f32>,
    material: Vec<Material>,
    /// Unit ray per pixel: normalising on the fly was a third of the frame time.
    rays: Vec<V3>,
}

/// Renders [`SceneSnapshot`]s; keeps the static background of the last few image sizes.
pub struct Renderer {
    camera: Camera,
    backgrounds: Vec<Background>,
    depth: Vec<f32>,
    shadow: Vec<bool>,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("camera", &self.camera)
            .field("cached_sizes", &self.backgrounds.len())
            .finish_non_exhaustive()
    }
}

/// Sizes whose background stays cached; more than a couple of sim cameras per arm would be unusual.
const MAX_CACHED_SIZES: usize = 4;

#[inline]
fn shade(colour: [f32; 3], normal: &V3) -> [f32; 3] {
    let light = V3::from(LIGHT).normalize();
    let k = AMBIENT + (1.0 - AMBIENT) * normal.dot(&light).max(0.0);
    colour.map(|c| c * k)
}

#[inline]
fn put(rgb: &mut [u8], index: usize, colour: [f32; 3]) {
    let o = index * 3;
    rgb[o] = colour[0].clamp(0.0, 255.0) as u8;
    rgb[o + 1] = colour[1].clamp(0.0, 255.0) as u8;
    rgb[o + 2] = colour[2].clamp(0.0, 255.0) as u8;
}

/// Ray–sphere: distance along the ray to the first hit in front of the origin.
#[inline]
fn hit_sphere(origin: &V3, dir: &V3, centre: &V3, radius: f32) -> Option<f32> {
    let oc = origin - centre;
    let b = oc.dot(dir);
    let c = oc.norm_squared() - radius * radius;
    let h = b * b - c;
    if h < 0.0 {
        return None;
    }
    let t = -b - h.sqrt();
    (t > 0.0).then_some(t)
}

/// Ray–capsule (segment `a`–`b`, radius `r`), after Inigo Quilez's closed form.
#[inline]
fn hit_capsule(origin: &V3, dir: &V3, a: &V3, b: &V3, r: f32) -> Option<f32> {
    let ba = b - a;
    let oa = origin - a;
    let baba = ba.norm_squared();
    let bard = ba.dot(dir);
    let baoa = ba.dot(&oa);
    let rdoa = dir.dot(&oa);
    let oaoa = oa.norm_squared();
    let qa = baba - bard * bard;
    let qb = baba * rdoa - baoa * bard;
    let qc = baba * oaoa - baoa * baoa - r * r * baba;
    let h = qb * qb - qa * qc;
    if h < 0.0 {
        return None;
    }
    if qa > 1e-9 {
        let t = (-qb - h.sqrt()) / qa;
        let y = baoa + t * bard;
        if y > 0.0 && y < baba {
            return (t > 0.0).then_some(t);
        }
        let cap = if y <= 0.0 { *a } else { *b };
        return hit_sphere(origin, dir, &cap, r);
    }
    // Looking along the axis: only a cap can be hit first.
    let ta = hit_sphere(origin, dir, a, r);
    let tb = hit_sphere(origin, dir, b, r);
    match (ta, tb) {
        (Some(x), Some(y)) => Some(x.min(y)),
        (x, y) => x.or(y),
    }
}

fn capsule_normal(p: &V3, a: &V3, b: &V3) -> V3 {
    let ba = b - a;
    let h = ((p - a).dot(&ba) / ba.norm_squared().max(1e-12)).clamp(0.0, 1.0);
    (p - a - ba * h).try_normalize(1e-9).unwrap_or_else(V3::z)
}

/// A dynamic primitive.
struct Capsule {
    a: V3,
    b: V3,
    radius: f32,
    colour: [f32; 3],
}

impl Renderer {
    pub fn new(camera: &SimCameraConfig) -> Self {
        Self {
            camera: Camera::new(camera),
            backgrounds: Vec::new(),
            depth: Vec::new(),
            shadow: Vec::new(),
        }
    }

    /// Draws `scene` into `out` as `width × height` packed RGB8 (resized as needed).
    pub fn render(&mut self, scene: &SceneSnapshot, width: u32, height: u32, out: &mut Vec<u8>) {
        let (w, h) = (width as usize, height as usize);
        out.clear();
        if w == 0 || h == 0 {
            return;
        }
        let key = [
            scene.basket_xy_m[0],
            scene.basket_xy_m[1],
            scene.basket_radius_m,
            scene.basket_height_m,
        ]
        .map(f64::to_bits);
        let cached = self
            .backgrounds
            .iter()
            .position(|b| b.width == w && b.height == h && b.key == key);
        let index = if let Some(i) = cached {
            i
        } else {
            if self.backgrounds.len() >= MAX_CACHED_SIZES {
                self.backgrounds.remove(0);
            }
            self.backgrounds.push(self.background(scene, w, h, key));
            self.backgrounds.len() - 1
        };
        let background = &self.backgrounds[index];
        out.extend_from_slice(&background.rgb);
        self.depth.clear();
        self.depth.extend_from_slice(&background.depth);
        self.shadow.clear();
        self.shadow.resize(w * h, false);
        let projection = Projection::new(&self.camera, w, h);

        let capsules = Self::arm_capsules(scene);
        let ball = V3::from_f64(&scene.ball_center_m);
        let ball_radius = scene.ball_radius_m as f32;
        self.draw_shadows(index, &projection, &capsules, &ball, ball_radius, out);
        for capsule in &capsules {
            self.draw_capsule(index, &projection, capsule, out);
        }
        let ball = Capsule {
            a: ball,
            b: ball,
            radius: ball_radius,
            colour: BALL,
        };
        self.draw_capsule(index, &projection, &ball, out);
    }

    /// The arm as capsules: base, links between joint origins, joint hubs, gripper jaws.
    fn arm_capsules(scene: &SceneSnapshot) -> Vec<Capsule> {
        let f = V3::from_f64;
        let links = &scene.links.links;
        let tcp = &scene.links.tcp;
        let mut capsules = Vec::with_capacity(16);
        let pan_axis = f(&links[0].translation.vector);
        capsules.push(Capsule {
            a: V3::new(pan_axis.x, pan_axis.y, 0.0),
            b: pan_axis,
            radius: 0.04,
            colour: LINK,
        });
        let radii = [0.024, 0.021, 0.018, 0.016];
        for i in 0..4 {
            let a = f(&links[i].translation.vector);
            let b = f(&links[i + 1].translation.vector);
            capsules.push(Capsule {
                a,
                b,
                radius: radii[i],
                colour: LINK,
            });
        }
        for link in links {
            let p = f(&link.translation.vector);
            capsules.push(Capsule {
                a: p,
                b: p,
                radius: 0.026,
                colour: JOINT,
            });
        }
        // The gripper as the world models it (`world::gripper_solids`): the wrist, the palm, and each finger
        // drawn as three rods across its width.
        let width = f(&(tcp.rotation * Vector3::x()));
        let tool = |x: f64, y: f64, z: f64| f(&(tcp * nalgebra::Point3::new(x, y, z)).coords);
        let root = tool(0.0, 0.0, FINGER_ROOT_M - 0.008);
        capsules.push(Capsule {
            a: f(&links[4].translation.vector),
            b: root,
            radius: 0.017,
            colour: LINK,
        });
        let finger_y = half_gap_m(scene.gripper_position) + FINGER_HALF_THICKNESS_M;
        capsules.push(Capsule {
            a: tool(0.0, -finger_y, FINGER_ROOT_M - 0.008),
            b: tool(0.0, finger_y, FINGER_ROOT_M - 0.008),
            radius: 0.008,
            colour: LINK,
        });
        let half_width = FINGER_HALF_WIDTH_M as f32;
        for side in [-1.0, 1.0] {
            let (a, b) = (
                tool(0.0, side * finger_y, FINGER_ROOT_M),
                tool(0.0, side * finger_y, FINGER_TIP_M),
            );
            for x in [-half_width, 0.0, half_width] {
                capsules.push(Capsule {
                    a: a + width * x,
                    b: b + width * x,
                    radius: FINGER_HALF_THICKNESS_M as f32,
                    colour: FINGER,
                });
            }
        }
        capsules
    }

    fn draw_capsule(
        &mut self,
        background: usize,
        projection: &Projection,
        capsule: &Capsule,
        out: &mut [u8],
    ) {
        let Some((x0, x1, y0, y1)) = projection.bbox(&self.camera, &[capsule.a, capsule.b], capsule.radius)
        else {
            return;
        };
        let (Some(pa), Some(pb)) = (
            projection.project(&self.camera, &capsule.a),
            projection.project(&self.camera, &capsule.b),
        ) else {
            return;
        };
        // A cheap 2D distance test to the projected axis rejects most of a diagonal link's bounding box
        // before the exact 3D intersection.
        let radius_px = projection.focal_px * capsule.radius / pa.2.min(pb.2) + 1.5;
        let (sa, sb) = (V2::new(pa.0, pa.1), V2::new(pb.0, pb.1));
        let sab = sb - sa;
        let sab2 = sab.norm_squared().max(1e-6);
        let eye = self.camera.eye;
        let rays = &self.backgrounds[background].rays;
        for y in y0..y1 {
            for x in x0..x1 {
                let s = V2::new(x as f32 + 0.5, y as f32 + 0.5);
                let h = ((s - sa).dot(sab) / sab2).clamp(0.0, 1.0);
                if (s - sa - sab * h).norm_squared() > radius_px * radius_px {
                    continue;
                }
                let index = y * projection.width + x;
                let dir = rays[index];
                let Some(t) = hit_capsule(&eye, &dir, &capsule.a, &capsule.b, capsule.radius) else {
                    continue;
                };
                if t >= self.depth[index] {
                    continue;
                }
                self.depth[index] = t;
                let p = eye + dir * t;
                put(
                    out,
                    index,
                    shade(capsule.colour, &capsule_normal(&p, &capsule.a, &capsule.b)),
                );
            }
        }
    }

    /// Darkens table and basket-floor pixels under the ball and the arm (straight-down projection).
    fn draw_shadows(
        &mut self,
        background: usize,
        projection: &Projection,
        capsules: &[Capsule],
        ball: &V3,
        ball_radius: f32,
        out: &mut [u8],
    ) {
        let ball_caster = Capsule {
            a: *ball,
            b: *ball,
            radius: ball_radius,
            colour: BALL,
        };
        let eye = self.camera.eye;
        let bg = &self.backgrounds[background];
        for caster in capsules.iter().chain(std::iter::once(&ball_caster)) {
            let footprint = [
                V3::new(caster.a.x, caster.a.y, 0.0),
                V3::new(caster.b.x, caster.b.y, 0.0),
            ];
            let Some((x0, x1, y0, y1)) = projection.bbox(&self.camera, &footprint, caster.radius) else {
                continue;
            };
            let (a, b) = (caster.a.xy(), caster.b.xy());
            let ab = b - a;
            let ab2 = ab.norm_squared().max(1e-12);
            let top = caster.a.z.max(caster.b.z);
            for y in y0..y1 {
                for x in x0..x1 {
                    let index = y * projection.width + x;
                    if self.shadow[index]
                        || !matches!(bg.material[index], Material::Table | Material::BasketFloor)
                    {
                        continue;
                    }
                    let p = eye + bg.rays[index] * bg.depth[index];
                    // The caster's shadow only falls on surfaces below it.
                    if p.z > top {
                        continue;
                    }
                    let h = ((p.xy() - a).dot(ab) / ab2).clamp(0.0, 1.0);
                    if (p.xy() - a - ab * h).norm_squared() <= caster.radius * caster.radius {
                        self.shadow[index] = true;
                        let o = index * 3;
                        for c in &mut out[o..o + 3] {
                            *c = (f32::from(*c) * 0.62) as u8;
                        }
                    }
                }
            }
        }
    }

    /// Ray casts the table and the basket for one image size.
    fn background(&self, scene: &SceneSnapshot, width: usize, height: usize, key: [u64; 4]) -> Background {
        let projection = Projection::new(&self.camera, width, height);
        let mut rgb = vec![0u8; width * height * 3];
        let mut depth = vec![f32::INFINITY; width * height];
        let mut material = vec![Material::Sky; width * height];
        let mut rays = Vec::with_capacity(width * height);
        let eye = self.camera.eye;
        let centre = V3::new(scene.basket_xy_m[0] as f32, scene.basket_xy_m[1] as f32, 0.0);
        let radius = scene.basket_radius_m as f32;
        let top = scene.basket_height_m as f32;
        let floor = BASKET_FLOOR_M as f32;
        for y in 0..height {
            let sky_k = y as f32 / height as f32;
            let sky = [0, 1, 2].map(|c| SKY_TOP[c] + (SKY_BOTTOM[c] - SKY_TOP[c]) * sky_k);
            for x in 0..width {
                let index = y * width + x;
                let dir = projection.ray(&self.camera, x, y);
                rays.push(dir);
                let mut best = (f32::INFINITY, Material::Sky, sky);
                if dir.z < 0.0 {
                    let t = -eye.z / dir.z;
                    let p = eye + dir * t;
                    if (TABLE_X_M.0..=TABLE_X_M.1).contains(&p.x)
                        && (TABLE_Y_M.0..=TABLE_Y_M.1).contains(&p.y)
                    {
                        // A 5 cm grid helps judge distances in the image.
                        let on_line = |v: f32| (v / 0.05 - (v / 0.05).round()).abs() < 0.04;
                        let colour = if on_line(p.x) || on_line(p.y) {
                            TABLE_LINE
                        } else {
                            TABLE
                        };
                        best = (t, Material::Table, shade(colour, &V3::z()));
                    }
                }
                if let Some(hit) = Self::basket_hit(&eye, &dir, &centre, radius, top, floor)
                    && hit.0 < best.0
                {
                    best = hit;
                }
                depth[index] = best.0;
                material[index] = best.1;
                put(&mut rgb, index, best.2);
            }
        }
        Background {
            width,
            height,
            key,
            rgb,
            depth,
            material,
            rays,
        }
    }

    /// Open-topped cylinder: the outside wall, or through the opening the inside wall or the floor.
    fn basket_hit(
        eye: &V3,
        dir: &V3,
        centre: &V3,
        radius: f32,
        top: f32,
        floor: f32,
    ) -> Option<(f32, Material, [f32; 3])> {
        let o = eye.xy() - centre.xy();
        let d = dir.xy();
        let a = d.norm_squared();
        if a < 1e-12 {
            return None;
        }
        let b = o.dot(d);
        let c = o.norm_squared() - radius * radius;
        let disc = b * b - a * c;
        if disc < 0.0 {
            return None;
        }
        let (t1, t2) = ((-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a);
        let z_at = |t: f32| eye.z + dir.z * t;
        let rim = |z: f32| top - z < 0.004;
        if t1 > 0.0 && (0.0..=top).contains(&z_at(t1)) {
            let p = *eye + dir * t1;
            let normal = V3::new(p.x - centre.x, p.y - centre.y, 0.0).normalize();
            let colour = if rim(p.z) { BASKET_RIM } else { BASKET_OUT };
            return Some((t1, Material::BasketWall, shade(colour, &normal)));
        }
        if z_at(t1) <= top {
            return None;
        }
        // Entered through the opening: floor first if the ray reaches it inside the wall.
        if dir.z < 0.0 {
            let tf = (floor - eye.z) / dir.z;
            if tf > 0.0 && tf <= t2 {
                return Some((tf, Material::BasketFloor, shade(BASKET_IN, &V3::z())));
            }
        }
        if t2 > 0.0 && (floor..=top).contains(&z_at(t2)) {
            let p = *eye + dir * t2;
            let normal = V3::new(centre.x - p.x, centre.y - p.y, 0.0).normalize();
            let colour = if rim(p.z) { BASKET_RIM } else { BASKET_IN };
            return Some((t2, Material::BasketWall, shade(colour, &normal)));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::super::{SimConfig, world::SimWorld};
    use super::*;

    fn render(world: &SimWorld, renderer: &mut Renderer, w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        renderer.render(&world.snapshot(), w, h, &mut out);
        out
    }

    #[test]
    fn draws_the_scene_and_changes_with_the_arm() {
        let config = SimConfig::default();
        let mut renderer = Renderer::new(&config.camera);
        let mut world = SimWorld::new(config).unwrap();
        let a = render(&world, &mut renderer, 160, 120);
        assert_eq!(a.len(), 160 * 120 * 3);
        // Red ball, orange links and blue basket are all in view.
        let count = |img: &[u8], f: &dyn Fn(u8, u8, u8) -> bool| {
            img.chunks(3).filter(|p| f(p[0], p[1], p[2])).count()
        };
        assert!(count(&a, &|r, g, b| r > 150 && g < 60 && b < 60) > 5, "ball");
        assert!(count(&a, &|r, g, b| r > 150 && g > 100 && b < 60) > 50, "links");
        assert!(count(&a, &|r, _, b| b > 120 && r < 90) > 20, "basket");
        let mut target = world.tool_pose();
        target.translation.vector += Vector3::new(0.05, 0.08, -0.05);
        world.apply_command(&crate::Command {
            seq: 1,
            robot_from_target: target,
            gripper_target: 1.0,
            issue_time_ns: 0,
            joint_targets_rad: None,
        });
        world.step(0.5);
        let b = render(&world, &mut renderer, 160, 120);
        let changed = a.chunks(3).zip(b.chunks(3)).filter(|(p, q)| p != q).count();
        assert!(changed > 200, "only {changed} pixels changed");
        // Same state, same image: the cache does not leak the previous frame.
        assert_eq!(render(&world, &mut renderer, 160, 120), b);
    }

    /// Wherever a reset puts the ball in the default area, the default camera shows it: a policy that learns
    /// from the image can see where to reach.
    #[test]
    fn the_camera_sees_the_ball_anywhere_in_its_area() {
        let config = SimConfig::default();
        let mut renderer = Renderer::new(&config.camera);
        let red = |img: &[u8]| {
            img.chunks(3)
                .filter(|p| p[0] > 150 && p[1] < 60 && p[2] < 60)
                .count()
        };
        let area = config.ball_area_m;
        for xy in area.corners().into_iter().chain([area.point_at(0.5, 0.5)]) {
            let world = SimWorld::new(SimConfig {
                ball_xy_m: xy,
                ..config.clone()
            })
            .unwrap();
            // A 2 cm ball about 0.55 m from the camera covers 40-70 pixels at 160x120; 20 means "in view and
            // not hidden behind the arm".
            let pixels = red(&render(&world, &mut renderer, 160, 120));
            assert!(pixels > 20, "ball at {xy:?}: {pixels} red pixels");
        }
    }

    #[test]
    fn degenerate_sizes_do_not_panic() {
        let config = SimConfig::default();
        let mut renderer = Renderer::new(&config.camera);
        let world = SimWorld::new(config).unwrap();
        assert!(render(&world, &mut renderer, 0, 10).is_empty());
        assert_eq!(render(&world, &mut renderer, 1, 1).len(), 3);
        for (w, h) in [(3, 2), (64, 48), (5, 7), (64, 48), (2, 2)] {
            assert_eq!(render(&world, &mut renderer, w, h).len(), (w * h * 3) as usize);
        }
    }
}
