//! Surfaces of the simulated world: what a ray hits, as a SemanticKITTI label, a
//! material class (what the physics layer keys its material effects on) and a
//! diffuse reflectivity in [0, 1] at the sensor's wavelength.

use serde::{Deserialize, Serialize};

/// SemanticKITTI class ids used by the simulator (low 16 bits of a label).
pub mod label {
    pub const UNLABELED: u32 = 0;
    pub const CAR: u32 = 10;
    pub const BICYCLE: u32 = 11;
    pub const PERSON: u32 = 30;
    pub const BICYCLIST: u32 = 31;
    pub const ROAD: u32 = 40;
    pub const SIDEWALK: u32 = 48;
    pub const BUILDING: u32 = 50;
    pub const FENCE: u32 = 51;
    pub const VEGETATION: u32 = 70;
    pub const TRUNK: u32 = 71;
    pub const TERRAIN: u32 = 72;
    pub const POLE: u32 = 80;
    pub const TRAFFIC_SIGN: u32 = 81;

    /// Human name of a class id (for plots and reports).
    pub fn name(class: u32) -> &'static str {
        match class {
            CAR => "car",
            BICYCLE => "bicycle",
            PERSON => "person",
            BICYCLIST => "bicyclist",
            ROAD => "road",
            SIDEWALK => "sidewalk",
            BUILDING => "building",
            FENCE => "fence",
            VEGETATION => "vegetation",
            TRUNK => "trunk",
            TERRAIN => "terrain",
            POLE => "pole",
            TRAFFIC_SIGN => "traffic-sign",
            _ => "other",
        }
    }
}

/// Material class of a hit surface.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum Material {
    /// No surface (no hit).
    None,
    Asphalt,
    Concrete,
    Plaster,
    Brick,
    /// Windows and windscreens: mostly transmissive, specular.
    Glass,
    /// Dark car paint: low diffuse reflectivity.
    DarkPaint,
    /// Bright (white, silver) car paint.
    BrightPaint,
    /// Tyres, rubber: very low reflectivity.
    Rubber,
    Metal,
    /// Retro-reflective sheeting of traffic signs and plates.
    RetroReflector,
    Foliage,
    Bark,
    Grass,
    Wood,
    Cloth,
}

impl Material {
    pub const ALL: [Material; 16] = [
        Material::None,
        Material::Asphalt,
        Material::Concrete,
        Material::Plaster,
        Material::Brick,
        Material::Glass,
        Material::DarkPaint,
        Material::BrightPaint,
        Material::Rubber,
        Material::Metal,
        Material::RetroReflector,
        Material::Foliage,
        Material::Bark,
        Material::Grass,
        Material::Wood,
        Material::Cloth,
    ];

    /// The id used in physics files (snake_case).
    pub fn name(self) -> &'static str {
        match self {
            Material::None => "none",
            Material::Asphalt => "asphalt",
            Material::Concrete => "concrete",
            Material::Plaster => "plaster",
            Material::Brick => "brick",
            Material::Glass => "glass",
            Material::DarkPaint => "dark_paint",
            Material::BrightPaint => "bright_paint",
            Material::Rubber => "rubber",
            Material::Metal => "metal",
            Material::RetroReflector => "retro_reflector",
            Material::Foliage => "foliage",
            Material::Bark => "bark",
            Material::Grass => "grass",
            Material::Wood => "wood",
            Material::Cloth => "cloth",
        }
    }
}

/// A surface kind: label, material, reflectivity, and for porous media (tree
/// crowns, bushes) the mean free path of a ray inside the volume.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surface {
    pub label: u32,
    pub material: Material,
    pub reflectivity: f32,
    /// 0 for solid surfaces; else the mean distance a ray travels inside the shape
    /// before it hits a leaf (exponential free path).
    pub mean_free_path_m: f32,
}

const fn solid(label: u32, material: Material, reflectivity: f32) -> Surface {
    Surface {
        label,
        material,
        reflectivity,
        mean_free_path_m: 0.0,
    }
}

/// Indices into [`SURFACES`].
pub mod surface {
    pub const ROAD: u16 = 0;
    pub const SIDEWALK: u16 = 1;
    pub const CURB: u16 = 2;
    pub const TERRAIN: u16 = 3;
    pub const PLASTER: u16 = 4;
    pub const BRICK: u16 = 5;
    pub const CONCRETE_WALL: u16 = 6;
    pub const WINDOW: u16 = 7;
    pub const CAR_DARK: u16 = 8;
    pub const CAR_BRIGHT: u16 = 9;
    pub const CAR_MID: u16 = 10;
    pub const CAR_GLASS: u16 = 11;
    pub const TYRE: u16 = 12;
    pub const PERSON: u16 = 13;
    pub const BICYCLIST: u16 = 14;
    pub const BICYCLE: u16 = 15;
    pub const POLE: u16 = 16;
    pub const SIGN_FACE: u16 = 17;
    pub const SIGN_BACK: u16 = 18;
    pub const FOLIAGE: u16 = 19;
    pub const BUSH: u16 = 20;
    pub const TRUNK: u16 = 21;
    pub const FENCE: u16 = 22;
    pub const WALL: u16 = 23;
    pub const HEDGE: u16 = 24;
    pub const PLATE: u16 = 25;
}

/// The surface table, indexed by [`surface`] constants. Reflectivities are
/// typical near-infrared (905 nm) diffuse values.
pub const SURFACES: [Surface; 26] = [
    solid(label::ROAD, Material::Asphalt, 0.18),
    solid(label::SIDEWALK, Material::Concrete, 0.32),
    solid(label::SIDEWALK, Material::Concrete, 0.38),
    solid(label::TERRAIN, Material::Grass, 0.45),
    solid(label::BUILDING, Material::Plaster, 0.55),
    solid(label::BUILDING, Material::Brick, 0.3),
    solid(label::BUILDING, Material::Concrete, 0.35),
    solid(label::BUILDING, Material::Glass, 0.08),
    solid(label::CAR, Material::DarkPaint, 0.05),
    solid(label::CAR, Material::BrightPaint, 0.6),
    solid(label::CAR, Material::Metal, 0.3),
    solid(label::CAR, Material::Glass, 0.08),
    solid(label::CAR, Material::Rubber, 0.03),
    solid(label::PERSON, Material::Cloth, 0.3),
    solid(label::BICYCLIST, Material::Cloth, 0.3),
    solid(label::BICYCLE, Material::Metal, 0.25),
    solid(label::POLE, Material::Metal, 0.35),
    solid(label::TRAFFIC_SIGN, Material::RetroReflector, 0.95),
    solid(label::TRAFFIC_SIGN, Material::Metal, 0.3),
    Surface {
        label: label::VEGETATION,
        material: Material::Foliage,
        reflectivity: 0.5,
        mean_free_path_m: 0.6,
    },
    Surface {
        label: label::VEGETATION,
        material: Material::Foliage,
        reflectivity: 0.45,
        mean_free_path_m: 0.3,
    },
    solid(label::TRUNK, Material::Bark, 0.3),
    solid(label::FENCE, Material::Wood, 0.3),
    solid(label::FENCE, Material::Concrete, 0.4),
    Surface {
        label: label::VEGETATION,
        material: Material::Foliage,
        reflectivity: 0.45,
        mean_free_path_m: 0.15,
    },
    solid(label::CAR, Material::RetroReflector, 0.9),
];
/// A typical material for a semantic class (effects keyed on material need one).
pub fn typical_material(class: u32) -> Material {
    match class {
        label::ROAD => Material::Asphalt,
        label::SIDEWALK => Material::Concrete,
        label::BUILDING => Material::Brick,
        label::CAR => Material::BrightPaint,
        label::VEGETATION => Material::Foliage,
        label::TRUNK => Material::Bark,
        label::TERRAIN => Material::Grass,
        label::POLE | label::BICYCLE => Material::Metal,
        label::TRAFFIC_SIGN => Material::RetroReflector,
        label::FENCE => Material::Wood,
        label::PERSON | label::BICYCLIST => Material::Cloth,
        _ => Material::Concrete,
    }
}
