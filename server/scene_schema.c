/*
 * The scene document's schema (SPEC §4): every field a client can set, with its default,
 * range, unit and one sentence of documentation, and where the compiled scene keeps it
 * (.store, .offset into render_scene_t, its items or scene_cloud_t; scene_compile.c). scene.c
 * validates documents against it and rpc.discover publishes it as components.schemas.Scene. The
 * defaults make a scene with no objects look deliberate: a camera a little above the origin looking
 * slightly down, a dark blue-grey background and a warm key light from the upper right, in front of
 * the scene.
 *
 * World coordinates are bounded at ±1e6 so that single-precision kernels keep millimetre
 * precision over the whole range; colours are linear RGB, up to 1000 to allow emitters.
 */
#include "scene_schema.h"

#include <math.h>
#include <stddef.h>

#define WORLD 1e6 /* Largest world coordinate accepted. */
/* 2^53 - 1, the largest n for which n and n + 1 are both exact doubles: the bound of seeds and
 * frame counts, as of request ids. */
#define MAX_SAFE 9007199254740991.0

static const double v_zero[3] = {0, 0, 0};
static const double v_one[3] = {1, 1, 1};
static const double v_up[3] = {0, 1, 0};
static const double cam_eye[3] = {0, 2, 8};
static const double cam_target[3] = {0, 0.5, 0};
/* Linear values; after the default ACES tone map this is about sRGB (59, 66, 85). */
static const double bg_color[3] = {0.05, 0.06, 0.08};
/* Up, to the right (+x) and towards the default camera (+z); normalised on validation. */
static const double light_dir[3] = {0.5, 1.0, 0.6};
static const double light_color[3] = {1.0, 0.96, 0.9};
static const double obj_color[3] = {0.8, 0.8, 0.8};

static const char *const shapes[] = {"box", "sphere", "tetrahedron", "plane", "mesh", NULL};
static const char *const tone_maps[] = {"none", "reinhard", "aces", NULL};
static const char *const volume_resolutions[] = {"full", "half", "quarter", NULL};
/* render_scene_t.volume_div of each volume_resolution. */
static const int volume_divs[] = {1, 2, 4};

/* Enums are compiled into ints (SCH_STORE_ENUM), in the order of their values above. */
_Static_assert(sizeof(shape_t) == sizeof(int) && sizeof(tone_map_t) == sizeof(int) &&
                   sizeof(volume_source_t) == sizeof(int) && sizeof(cloud_rules_t) == sizeof(int),
               "an enum compiled from a schema ENUM is an int");
_Static_assert(SHAPE_BOX == 0 && SHAPE_SPHERE == 1 && SHAPE_TETRAHEDRON == 2 && SHAPE_PLANE == 3 &&
                   SHAPE_MESH == 4 && TONE_NONE == 0 && TONE_REINHARD == 1 && TONE_ACES == 2,
               "shape_t and tone_map_t follow the order of their schema values");

static const sch_field_t camera_fields[] = {
    {.name = "eye",
     .type = SCH_VEC3,
     .desc = "Position of the camera.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = cam_eye,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(render_scene_t, camera.eye)},
    {.name = "target",
     .type = SCH_VEC3,
     .desc = "Point the camera looks at; must differ from eye.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = cam_target,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(render_scene_t, camera.target)},
    {.name = "up",
     .type = SCH_VEC3,
     .desc = "Direction that appears upwards in the image; must not be parallel to the view.",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = v_up,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(render_scene_t, camera.up)},
    {.name = "fov_y",
     .type = SCH_NUMBER,
     .desc = "Vertical field of view.",
     .unit = "degrees",
     .min = 1,
     .max = 179,
     .def = 45,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, camera.fov_y)},
    {.name = "near",
     .type = SCH_NUMBER,
     .desc = "Distance along the ray where rendering starts; must be less than far.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def = 0.01,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, camera.near_)},
    {.name = "far",
     .type = SCH_NUMBER,
     .desc = "Distance along the ray beyond which nothing is drawn.",
     .unit = "world units",
     .min = 0,
     .max = 1e9,
     .def = 1000,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, camera.far_)},
    {0},
};

static const sch_field_t light_fields[] = {
    {.name = "direction",
     .type = SCH_VEC3,
     .desc = "Direction from the scene towards the light (a distant sun); normalised on input.",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = light_dir,
     .flags = SCH_UNIT_VEC,
     .store = SCH_STORE_UNIT3F,
     .offset = offsetof(render_scene_t, light.direction)},
    {.name = "color",
     .type = SCH_VEC3,
     .desc = "Linear RGB colour of the light.",
     .min = 0,
     .max = 1000,
     .def_vec = light_color,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(render_scene_t, light.color)},
    {.name = "intensity",
     .type = SCH_NUMBER,
     .desc = "Multiplier applied to the light's colour.",
     .min = 0,
     .max = 1e4,
     .def = 3,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, light.intensity)},
    {.name = "ambient",
     .type = SCH_NUMBER,
     .desc = "Fraction of the light that reaches surfaces in shadow or facing away.",
     .min = 0,
     .max = 1,
     .def = 0.15,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, light.ambient)},
    {.name = "shadow_map",
     .type = SCH_INTEGER,
     .desc = "Side of the light's shadow map.",
     .unit = "pixels",
     .min = 16,
     .max = 8192,
     .def = 1024,
     .store = SCH_STORE_INT,
     .offset = offsetof(render_scene_t, light.shadow_map)},
    {0},
};

static const sch_field_t object_fields[] = {
    {.name = "id",
     .type = SCH_STRING,
     .desc = "Name of the object for clients; unique within the scene when not empty.",
     .max = 63,
     .def_str = ""},
    {.name = "shape",
     .type = SCH_ENUM,
     .desc = "Kind of primitive, or a mesh loaded from file.",
     .enum_values = shapes,
     .flags = SCH_REQUIRED,
     .store = SCH_STORE_ENUM,
     .offset = offsetof(robject_t, shape)},
    {.name = "position",
     .type = SCH_VEC3,
     .desc = "Translation of the object's centre.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = v_zero,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(robject_t, position)},
    {.name = "scale",
     .type = SCH_VEC3,
     .desc = "Size along the object's own axes (a unit box or a sphere of diameter 1 at scale 1).",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def_vec = v_one,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(robject_t, scale)},
    {.name = "rotation",
     .type = SCH_VEC3,
     .desc = "Rotation about the X, then Y, then Z axis.",
     .unit = "degrees",
     .min = -36000,
     .max = 36000,
     .def_vec = v_zero,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(robject_t, rotation)},
    {.name = "color",
     .type = SCH_VEC3,
     .desc = "Linear RGB albedo of the Lambert surface.",
     .min = 0,
     .max = 1000,
     .def_vec = obj_color,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(robject_t, color)},
    {.name = "file",
     .type = SCH_STRING,
     .desc = "Wavefront OBJ file for a mesh, relative to the server's data directory.",
     .max = 1023,
     .flags = SCH_NO_DEFAULT},
    {0},
};

static const sch_field_t object_item = {
    .name = "object",
    .type = SCH_OBJECT,
    .desc = "An opaque, Lambert-lit, shadow-casting object.",
    .fields = object_fields,
};

/* Waves (SPEC §5.1). The defaults suit a scene of unit scale such as the default one: a glow
 * about a unit across around the default camera's target, its beam reaching two units along
 * +x, in a cyan blue that the tone map turns towards white where the glow is clamped. H, the
 * integral along the ray that the clamp bounds, has the units of a and b. */
static const double wave_center[3] = {0, 0.5, 0};
static const double wave_direction[3] = {1, 0, 0};
static const double wave_color[3] = {0.35, 0.8, 1.6};

static const char *const wave_animatable[] = {"center", "direction", "a",     "b",     "length",
                                              "radius", "softening", "clamp", "color", NULL};
static const char *const interps[] = {"linear", "smooth", NULL};

static const sch_field_t anim_key_fields[] = {
    {.name = "t",
     .type = SCH_NUMBER,
     .desc = "Simulation time of the key; strictly greater than the previous key's.",
     .unit = "seconds",
     .min = 0,
     .max = 1e12,
     .flags = SCH_REQUIRED},
    {.name = "value",
     .type = SCH_ANY,
     .desc = "Value of the field at t: a number, or [x, y, z] for center, direction and color; "
             "within the field's range.",
     .flags = SCH_REQUIRED},
    {0},
};

static const sch_field_t anim_key_item = {
    .name = "key",
    .type = SCH_OBJECT,
    .desc = "One keyframe.",
    .fields = anim_key_fields,
};

static const sch_field_t wave_anim_fields[] = {
    {.name = "field",
     .type = SCH_ENUM,
     .desc = "The wave field animated; each field at most once per wave.",
     .enum_values = wave_animatable,
     .flags = SCH_REQUIRED},
    {.name = "target",
     .type = SCH_ANY,
     .desc = "Toward-target animation: the value the field moves to, then stays at: a number, or "
             "[x, y, z] for center, direction and color; within the field's range. Needs rate; "
             "excludes keys.",
     .flags = SCH_NO_DEFAULT},
    {.name = "rate",
     .type = SCH_NUMBER,
     .desc = "Speed of a toward-target animation: the field's units per second (a vec3 moves "
             "along the straight line to the target; direction turns along the great circle "
             "in radians per second).",
     .unit = "field units per second",
     .min = 0,
     .max = 1e9,
     .flags = SCH_POSITIVE | SCH_NO_DEFAULT},
    {.name = "keys",
     .type = SCH_ARRAY,
     .desc = "Keyframe animation: at least one key, t strictly increasing; the field takes the "
             "interpolated value at sim.time, the first key's value before it and the last "
             "key's after it. Excludes target and rate. All of a scene's entries together hold "
             "at most limits.keyframes keys.",
     .max = 1024,
     .items = &anim_key_item,
     .flags = SCH_NO_DEFAULT},
    {.name = "interp",
     .type = SCH_ENUM,
     .desc = "Keyframes only: linear, or smooth (smoothstep easing between each pair of keys; "
             "direction is turned along the great circle either way).",
     .def_str = "linear",
     .enum_values = interps,
     .flags = SCH_NO_DEFAULT | SCH_SHOW_DEFAULT},
    {.name = "loop",
     .type = SCH_BOOL,
     .desc = "Keyframes only: after the last key, start again from the first (the period is the "
             "last key's t minus the first's).",
     .flags = SCH_NO_DEFAULT | SCH_SHOW_DEFAULT},
    {0},
};

static const sch_field_t wave_anim_item = {
    .name = "animation",
    .type = SCH_OBJECT,
    .desc = "Motion or deformation of one wave field, advanced by sim.step and sim.play: either "
            "toward a target at a rate (target, rate) or by keyframes (keys, interp, loop). The "
            "current value is written into the field, where scene.get shows it.",
    .fields = wave_anim_fields,
};

static const sch_field_t wave_fields[] = {
    {.name = "id",
     .type = SCH_STRING,
     .desc = "Name of the wave for clients; unique among the waves when not empty.",
     .max = 63,
     .def_str = ""},
    {.name = "center",
     .type = SCH_VEC3,
     .desc = "Centre M of the sphere term, where the beam starts.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = wave_center,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rwave_t, center)},
    {.name = "direction",
     .type = SCH_VEC3,
     .desc = "Direction D of the beam; normalised on input, the zero vector is refused.",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = wave_direction,
     .flags = SCH_UNIT_VEC,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rwave_t, direction)},
    {.name = "a",
     .type = SCH_NUMBER,
     .desc = "Strength of the sphere term a/sqrt(r^2 + softening^2); a and b are not both 0 "
             "unless one of them is animated.",
     .min = 0,
     .max = 1e6,
     .def = 1,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, a)},
    {.name = "b",
     .type = SCH_NUMBER,
     .desc = "Strength of the beam term b/sqrt(q^2 + softening^2), q the distance to the "
             "segment from center to center + length * direction.",
     .min = 0,
     .max = 1e6,
     .def = 0.5,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, b)},
    {.name = "length",
     .type = SCH_NUMBER,
     .desc = "Length L of the beam from center along direction; 0 leaves a sphere. Animate it "
             "from 0 to grow the beam out of the centre.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def = 2,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, length)},
    {.name = "radius",
     .type = SCH_NUMBER,
     .desc = "Support radius R: the density is zero farther than this from the beam's segment "
             "(a capsule).",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def = 3,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, radius)},
    {.name = "softening",
     .type = SCH_NUMBER,
     .desc = "Softening epsilon: keeps the density finite at the centre and on the axis; the "
             "core's apparent thickness.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def = 0.05,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, softening)},
    {.name = "clamp",
     .type = SCH_NUMBER,
     .desc = "Largest H shown (the ray's integral of the density, in the units of a and b): "
             "min(H, clamp) / clamp scales color.",
     .min = 0,
     .max = 1e6,
     .def = 4,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(rwave_t, clamp)},
    {.name = "color",
     .type = SCH_VEC3,
     .desc = "Linear RGB added where H reaches clamp; above 1 blooms towards white.",
     .min = 0,
     .max = 1000,
     .def_vec = wave_color,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rwave_t, color)},
    {.name = "animate",
     .type = SCH_ARRAY,
     .desc = "Motion and deformation of this wave's numeric fields (thesis 2.3).",
     .max = 16,
     .items = &wave_anim_item},
    {0},
};

static const sch_field_t wave_item = {
    .name = "wave",
    .type = SCH_OBJECT,
    .desc = "An energy wave: a glowing sphere at center with a beam along direction, integrated "
            "in closed form along each ray and added over the objects (SPEC 5.1).",
    .fields = wave_fields,
};

static const sch_field_t sim_fields[] = {
    {.name = "time",
     .type = SCH_NUMBER,
     .desc = "Simulation clock.",
     .unit = "seconds",
     .min = 0,
     .max = 1e12,
     .store = SCH_STORE_F64,
     .offset = offsetof(render_scene_t, time)},
    {.name = "frame",
     .type = SCH_INTEGER,
     .desc = "Number of simulation steps taken.",
     .min = 0,
     .max = MAX_SAFE,
     .store = SCH_STORE_U64,
     .offset = offsetof(render_scene_t, frame)},
    {.name = "dt",
     .type = SCH_NUMBER,
     .desc = "Length of one simulation step.",
     .unit = "seconds",
     .min = 0,
     .max = 1,
     .def = 1.0 / 60.0,
     .flags = SCH_POSITIVE},
    {.name = "playing",
     .type = SCH_BOOL,
     .desc = "Whether the server advances the simulation by itself (sim.play)."},
    {.name = "seed",
     .type = SCH_INTEGER,
     .desc = "Seed of every random choice the simulations make.",
     .min = 0,
     .max = MAX_SAFE},
    {0},
};

static const sch_field_t render_fields[] = {
    {.name = "exposure",
     .type = SCH_NUMBER,
     .desc = "Exposure applied before tone mapping: linear values are scaled by 2^exposure.",
     .unit = "stops",
     .min = -20,
     .max = 20,
     .store = SCH_STORE_F32,
     .offset = offsetof(render_scene_t, exposure)},
    {.name = "tone_map",
     .type = SCH_ENUM,
     .desc = "Curve mapping linear light to display values.",
     .def_str = "aces",
     .enum_values = tone_maps,
     .store = SCH_STORE_ENUM,
     .offset = offsetof(render_scene_t, tone_map)},
    {.name = "transparent_background",
     .type = SCH_BOOL,
     .desc = "Draw background pixels as transparent black (premultiplied alpha, for "
             "compositing) unless a frame's 'background' param says otherwise.",
     .store = SCH_STORE_BOOL,
     .offset = offsetof(render_scene_t, transparent_background)},
    {.name = "volume_resolution",
     .type = SCH_ENUM,
     .desc = "Resolution of the volumes pass (volumes and the cloud): full, or half or a quarter "
             "of the frame's width and height, composited over the full frame with the opaque "
             "depth deciding which low-resolution pixels each pixel takes: 4 or 16 times fewer "
             "rays, softer shafts.",
     .def_str = "full",
     .enum_values = volume_resolutions,
     .store = SCH_STORE_ENUM,
     .offset = offsetof(render_scene_t, volume_div),
     .enum_codes = volume_divs},
    {.name = "antialias",
     .type = SCH_INTEGER,
     .desc = "Samples per pixel along each axis: a beauty frame is rendered at antialias times "
             "its width and height and each pixel is the mean of its antialias x antialias "
             "samples (after the tone map for png and rgba8). Lowered for a frame whose samples "
             "would pass 4096 x 4096; depth and wave_h take one sample per pixel.",
     .min = 1,
     .max = 4,
     .def = 1,
     .store = SCH_STORE_INT,
     .offset = offsetof(render_scene_t, antialias)},
    {0},
};

static const double fluid_gravity[3] = {0, -9.81, 0};
static const double fluid_min[3] = {-5, -5, -5};
static const double fluid_max[3] = {5, 5, 5};
/* A pale blue-green tint, close to clear water seen through a few metres. */
static const double fluid_color[3] = {0.8, 0.93, 0.95};

static const sch_field_t fluid_bounds_fields[] = {
    {.name = "min",
     .type = SCH_VEC3,
     .desc = "Lowest corner of the tank; below max on every axis.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = fluid_min},
    {.name = "max",
     .type = SCH_VEC3,
     .desc = "Highest corner of the tank; above min on every axis.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = fluid_max},
    {0},
};

static const sch_field_t fluid_material_fields[] = {
    {.name = "color",
     .type = SCH_VEC3,
     .desc = "Transmission tint of the liquid, linear RGB.",
     .min = 0,
     .max = 1,
     .def_vec = fluid_color,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rfluid_t, color)},
    {.name = "ior",
     .type = SCH_NUMBER,
     .desc = "Index of refraction, for the Fresnel term.",
     .min = 1,
     .max = 3,
     .def = 1.33,
     .store = SCH_STORE_F32,
     .offset = offsetof(rfluid_t, ior)},
    {.name = "roughness",
     .type = SCH_NUMBER,
     .desc = "Spread of the specular highlight, 0 (mirror) to 1.",
     .min = 0,
     .max = 1,
     .def = 0.1,
     .store = SCH_STORE_F32,
     .offset = offsetof(rfluid_t, roughness)},
    {0},
};

/* Emitters (sim_fluid.h: FLUID_MAX_EMITTERS) and the most particles a scene's own fields can
 * make: SPEC §3's default limits.particles, so that a document cannot ask for more memory than
 * fluid.set_particles could fill. */
#define FLUID_EMITTERS 16
#define FLUID_PARTICLES (1 << 20)
static const char *const emit_shapes[] = {"sphere", "box", NULL};
static const double emit_size[3] = {0.5, 0.5, 0.5};

static const sch_field_t fluid_emitter_fields[] = {
    {.name = "shape",
     .type = SCH_ENUM,
     .desc = "Region new particles appear in, uniformly at random: a ball of radius 'radius' or "
             "a box of edges 'size', centred on position.",
     .enum_values = emit_shapes,
     .def_str = "sphere"},
    {.name = "position",
     .type = SCH_VEC3,
     .desc = "Centre of the emitter; must lie inside fluid.bounds (particles falling outside "
             "them are moved onto the nearest wall).",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = v_zero},
    {.name = "radius",
     .type = SCH_NUMBER,
     .desc = "Radius of a sphere emitter.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def = 0.25},
    {.name = "size",
     .type = SCH_VEC3,
     .desc = "Edge lengths of a box emitter along x, y and z.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .def_vec = emit_size},
    {.name = "rate",
     .type = SCH_NUMBER,
     .desc = "Particles added per second of simulated time (fractions carry over between "
             "steps); emitting stops while the fluid holds max_particles. About |velocity| × "
             "the emitter's cross-section / (h/2)^3 keeps a stream at rest density; much more "
             "and the new particles burst apart.",
     .unit = "particles/second",
     .min = 0,
     .max = 1e7,
     .def = 200},
    {.name = "velocity",
     .type = SCH_VEC3,
     .desc = "Velocity every new particle starts with.",
     .unit = "m/s",
     .min = -1000,
     .max = 1000,
     .def_vec = v_zero},
    {0},
};

static const sch_field_t fluid_emitter_item = {
    .name = "emitter",
    .type = SCH_OBJECT,
    .desc = "A source of new particles while the fluid is simulated (sim.step, sim.play).",
    .fields = fluid_emitter_fields,
};

static const sch_field_t fluid_block_fields[] = {
    {.name = "origin",
     .type = SCH_VEC3,
     .desc = "Centre of the block's first particle: its lowest x, y and z.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = v_zero},
    {.name = "spacing",
     .type = SCH_NUMBER,
     .desc = "Distance between neighbouring particles of the cubic lattice; 0 takes h/2, the "
             "spacing at which the default particle_mass has rest_density.",
     .unit = "world units",
     .min = 0,
     .max = WORLD},
    {.name = "nx",
     .type = SCH_INTEGER,
     .desc = "Particles along x in each layer.",
     .min = 1,
     .max = 65536,
     .def = 24},
    {.name = "nz",
     .type = SCH_INTEGER,
     .desc = "Particles along z in each layer; layers of nx × nz stack upwards (+y), the last "
             "one partly filled (x fastest, then z), until the block holds count.",
     .min = 1,
     .max = 65536,
     .def = 24},
    {.name = "count",
     .type = SCH_INTEGER,
     .desc = "Lattice points in the block; every one must lie inside fluid.bounds. Points "
             "inside a sphere, box or plane of 'objects' (the fluid's colliders) are left out, "
             "so fluid.count may be smaller.",
     .min = 1,
     .max = FLUID_PARTICLES,
     .flags = SCH_REQUIRED},
    {.name = "velocity",
     .type = SCH_VEC3,
     .desc = "Velocity every particle of the block starts with.",
     .unit = "m/s",
     .min = -1000,
     .max = 1000,
     .def_vec = v_zero},
    {0},
};

static const sch_field_t fluid_block_item = {
    .name = "block",
    .type = SCH_OBJECT,
    .desc = "A block of particles on a cubic lattice, stacked in layers of nx × nz (the paper's "
            "Table 1 set-up is 24 × 24 layers of spacing h/2).",
    .fields = fluid_block_fields,
};

static const sch_field_t fluid_fields[] = {
    {.name = "enabled",
     .type = SCH_BOOL,
     .desc = "Whether the particles are simulated by sim.step and sim.play, and drawn."},
    {.name = "h",
     .type = SCH_NUMBER,
     .desc = "SPH support radius and metaball radius; particles sit about h/2 apart at rest.",
     .unit = "world units",
     .min = 0.001,
     .max = 100,
     .def = 0.61,
     .store = SCH_STORE_F32,
     .offset = offsetof(rfluid_t, h)},
    {.name = "threshold",
     .type = SCH_NUMBER,
     .desc = "Metaball iso level T: the surface is where sqrt of the summed field equals T.",
     .min = 0,
     .max = 100,
     .def = 0.765625,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F32,
     .offset = offsetof(rfluid_t, threshold)},
    {.name = "particle_mass",
     .type = SCH_NUMBER,
     .desc = "Mass of one particle: 0, the mass for which a cubic lattice of spacing h/2 has "
             "exactly rest_density, or from 1e-12.",
     .unit = "kg",
     .min = 0,
     .max = 1e9},
    {.name = "rest_density",
     .type = SCH_NUMBER,
     .desc = "Density the fluid relaxes to.",
     .unit = "kg/m^3",
     .min = 1e-3,
     .max = 1e6,
     .def = 1000},
    {.name = "stiffness",
     .type = SCH_NUMBER,
     .desc = "k of the equation of state p = k (rho - rest_density); the sound speed is sqrt(k).",
     .unit = "m^2/s^2",
     .min = 1e-3,
     .max = 1e8,
     .def = 1000},
    {.name = "viscosity",
     .type = SCH_NUMBER,
     .desc = "Dynamic viscosity mu of the viscosity term.",
     .unit = "Pa s",
     .min = 0,
     .max = 1e6,
     .def = 50},
    {.name = "gravity",
     .type = SCH_VEC3,
     .desc = "Acceleration of gravity on every particle.",
     .unit = "m/s^2",
     .min = -1000,
     .max = 1000,
     .def_vec = fluid_gravity},
    {.name = "bounds",
     .type = SCH_OBJECT,
     .desc = "The tank: particles never leave it, and fluid.set_particles refuses any outside.",
     .fields = fluid_bounds_fields},
    {.name = "material",
     .type = SCH_OBJECT,
     .desc = "How the liquid surface is shaded.",
     .fields = fluid_material_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "emitters",
     .type = SCH_ARRAY,
     .desc = "Sources that add particles while the fluid is simulated.",
     .max = FLUID_EMITTERS,
     .items = &fluid_emitter_item},
    {.name = "initial",
     .type = SCH_ARRAY,
     .desc = "Blocks of particles the fluid starts with: when the scene is created and whenever "
             "this field's value changes, every particle is replaced by these blocks (an empty "
             "array removes them); fluid.set_particles replaces them again.",
     .max = 16,
     .items = &fluid_block_item},
    {.name = "max_particles",
     .type = SCH_INTEGER,
     .desc = "Most particles the emitters fill the fluid to (limits.particles caps it too); "
             "the blocks of 'initial' together may not hold more.",
     .min = 1,
     .max = FLUID_PARTICLES,
     .def = 65536},
    {.name = "count",
     .type = SCH_INTEGER,
     .desc = "READ-ONLY: the number of particles (from initial, the emitters or "
             "fluid.set_particles); any value "
             "written here is replaced by the real count.",
     .min = 0,
     .max = 1 << 26},
    {0},
};

/* Volumes (SPEC §5.3). The defaults make a soft patch of mist two units across standing on the
 * ground at the origin, thin enough to see through: about 0.5 of the light crosses its width. */
static const double vol_min[3] = {-1, 0, -1};
static const double vol_max[3] = {1, 2, 1};
static const double vol_albedo[3] = {0.9, 0.9, 0.9};
static const char *const vol_sources[] = {"noise", "file", NULL};
static const char *const vol_formats[] = {"u8", "f32", NULL};
_Static_assert(VOLUME_NOISE == 0 && VOLUME_GRID == 1, "volume_source_t follows vol_sources");

static const sch_field_t vol_bounds_fields[] = {
    {.name = "min",
     .type = SCH_VEC3,
     .desc = "Lowest corner of the volume's axis-aligned box; below max on every axis.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = vol_min,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rvolume_t, min)},
    {.name = "max",
     .type = SCH_VEC3,
     .desc = "Highest corner of the volume's box; above min on every axis.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = vol_max,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rvolume_t, max)},
    {0},
};

static const sch_field_t volume_fields[] = {
    {.name = "id",
     .type = SCH_STRING,
     .desc = "Name of the volume for clients; unique within the scene when not empty.",
     .max = 63,
     .def_str = ""},
    {.name = "source",
     .type = SCH_ENUM,
     .desc = "Where the density d comes from: seeded fBm value noise (d in [0, 1], faded to 0 "
             "over the outer 15% of the box), or a raw grid file (format, dims) spanning the "
             "box, interpolated trilinearly.",
     .enum_values = vol_sources,
     .def_str = "noise",
     .store = SCH_STORE_ENUM,
     .offset = offsetof(rvolume_t, source)},
    {.name = "file",
     .type = SCH_STRING,
     .desc = "For source file: raw densities relative to the server's data directory, x "
             "fastest, then y, then z, dims[0] x dims[1] x dims[2] values of the given format.",
     .max = 1023,
     .flags = SCH_NO_DEFAULT},
    {.name = "format",
     .type = SCH_ENUM,
     .desc = "For source file: u8 (d = byte / 255) or f32 (little-endian floats, finite and "
             "non-negative).",
     .enum_values = vol_formats,
     .def_str = "f32"},
    {.name = "dims",
     .type = SCH_VEC3,
     .desc = "For source file: the grid's voxels along x, y and z; integers from 1 to the "
             "server's cloud_side limit (server.info).",
     .unit = "voxels",
     .min = 1,
     .max = INFINITY, /* Checked against the limit by scene.c (-32003), published by discover. */
     .flags = SCH_NO_DEFAULT},
    {.name = "bounds",
     .type = SCH_OBJECT,
     .desc = "The volume's axis-aligned box; nothing is drawn outside it.",
     .fields = vol_bounds_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "density",
     .type = SCH_NUMBER,
     .desc = "Extinction coefficient where d = 1: light crossing a length s of uniform d = 1 "
             "keeps exp(-density * s) of itself.",
     .unit = "1/world unit",
     .min = 0,
     .max = 1e4,
     .def = 0.35,
     .store = SCH_STORE_F32,
     .offset = offsetof(rvolume_t, density)},
    {.name = "albedo",
     .type = SCH_VEC3,
     .desc = "Single-scattering albedo, linear RGB: the fraction of the extinguished light that "
             "is scattered rather than absorbed.",
     .min = 0,
     .max = 1,
     .def_vec = vol_albedo,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(rvolume_t, albedo)},
    {.name = "samples",
     .type = SCH_INTEGER,
     .desc = "Samples per ray, evenly spaced between where the ray enters the volume and "
             "where it leaves it or meets an opaque object.",
     .min = 1,
     .max = 1024,
     .def = 32,
     .store = SCH_STORE_INT,
     .offset = offsetof(rvolume_t, samples)},
    {.name = "phase_g",
     .type = SCH_NUMBER,
     .desc = "Henyey-Greenstein asymmetry of the scattering: 0 even, towards 1 forward (bright "
             "shafts when looking towards the light).",
     .min = -0.95,
     .max = 0.95,
     .def = 0,
     .store = SCH_STORE_F32,
     .offset = offsetof(rvolume_t, phase_g)},
    {.name = "seed",
     .type = SCH_INTEGER,
     .desc = "For source noise: the noise's seed; the same seed gives the same volume.",
     .min = 0,
     .max = 4294967295.0,
     .def = 1,
     .store = SCH_STORE_U32,
     .offset = offsetof(rvolume_t, seed)},
    {.name = "noise_scale",
     .type = SCH_NUMBER,
     .desc = "For source noise: the size of the largest noise features.",
     .unit = "world units",
     .min = 0.001,
     .max = WORLD,
     .def = 1,
     .store = SCH_STORE_F32,
     .offset = offsetof(rvolume_t, noise_scale)},
    {0},
};

static const sch_field_t volume_item = {
    .name = "volume",
    .type = SCH_OBJECT,
    .desc = "A participating medium in a box (mist, smoke, dust), drawn around the objects with "
            "single scattering and the objects' shadows (light shafts); SPEC 5.3.",
    .fields = volume_fields,
};

/* The cloud (SPEC 5.4): a 64³ automaton over a 6-unit cube standing on y = 0 at the centre. */
static const double cloud_grid[3] = {64, 64, 64};
static const double cloud_origin[3] = {-3, 0, -3};
static const double cloud_albedo[3] = {0.95, 0.95, 0.95};
static const char *const cloud_rules[] = {"kuromiya", "dobashi", NULL};
_Static_assert(CLOUD_KUROMIYA == 0 && CLOUD_DOBASHI == 1, "cloud_rules_t follows cloud_rules");

static const sch_field_t cloud_init_fields[] = {
    {.name = "hum",
     .type = SCH_NUMBER,
     .desc = "Probability that a cell starts with humidity (inside an ellipsoid, when there "
             "are any).",
     .min = 0,
     .max = 1,
     .def = 0.6,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, init_hum)},
    {.name = "act",
     .type = SCH_NUMBER,
     .desc = "Probability that a humid cell also starts active (a seed of growth).",
     .min = 0,
     .max = 1,
     .def = 0.0005,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, init_act)},
    {.name = "steps",
     .type = SCH_INTEGER,
     .desc = "Automaton steps taken at seeding, before the first frame, so that a scene can "
             "open on a grown cloud (its density shown unsmoothed); at most 2^32 cell-steps "
             "(grid cells x steps).",
     .min = 0,
     .max = 256,
     .def = 0,
     .store = SCH_STORE_U32,
     .offset = offsetof(scene_cloud_t, init_steps)},
    {0},
};

static const sch_field_t cloud_ellipsoid_fields[] = {
    {.name = "center",
     .type = SCH_VEC3,
     .desc = "Centre of the ellipsoid.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .flags = SCH_REQUIRED},
    {.name = "radii",
     .type = SCH_VEC3,
     .desc = "Semi-axes along x, y and z; each above 0.",
     .unit = "world units",
     .min = 0,
     .max = WORLD,
     .flags = SCH_REQUIRED},
    {0},
};
static const sch_field_t cloud_ellipsoid_item = {
    .type = SCH_OBJECT,
    .desc = "An ellipsoid where humidity and activation are supplied, most at its centre.",
    .fields = cloud_ellipsoid_fields};

static const sch_field_t cloud_fields[] = {
    {.name = "enabled",
     .type = SCH_BOOL,
     .desc = "Whether the cloud exists: stepped by sim.step and sim.play and drawn. Enabling it "
             "seeds fresh cells.",
     .store = SCH_STORE_BOOL,
     .offset = offsetof(scene_cloud_t, enabled)},
    {.name = "grid",
     .type = SCH_VEC3,
     .desc = "Cells along x, y and z: integers from 1 to limits.cloud_side. Changing it seeds "
             "fresh cells.",
     .unit = "cells",
     .min = 1,
     .max = INFINITY, /* Checked against the limit by scene.c (-32003), published by discover. */
     .def_vec = cloud_grid,
     .store = SCH_STORE_VEC3U32,
     .offset = offsetof(scene_cloud_t, n)},
    {.name = "origin",
     .type = SCH_VEC3,
     .desc = "Lowest corner of the grid; the cloud fills origin .. origin + grid × voxel.",
     .unit = "world units",
     .min = -WORLD,
     .max = WORLD,
     .def_vec = cloud_origin,
     .store = SCH_STORE_VEC3D,
     .offset = offsetof(scene_cloud_t, origin)},
    {.name = "voxel",
     .type = SCH_NUMBER,
     .desc = "Edge of one cell.",
     .unit = "world units",
     .min = 0,
     .max = 1000,
     .def = 0.09375,
     .flags = SCH_POSITIVE,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, voxel)},
    {.name = "rules",
     .type = SCH_ENUM,
     .desc = "kuromiya: the deterministic growth rules of SPEC 5.4; dobashi: the same plus "
             "random extinction (p_ext), supply (p_hum, p_act) and wind.",
     .def_str = "kuromiya",
     .enum_values = cloud_rules,
     .store = SCH_STORE_ENUM,
     .offset = offsetof(scene_cloud_t, params.rules)},
    {.name = "p_ext",
     .type = SCH_NUMBER,
     .desc = "dobashi: probability per step that a cloud cell vanishes.",
     .min = 0,
     .max = 1,
     .def = 0.002,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, params.p_ext)},
    {.name = "p_hum",
     .type = SCH_NUMBER,
     .desc = "dobashi: probability per step that a cell gains humidity (times the ellipsoids' "
             "shape, when there are any).",
     .min = 0,
     .max = 1,
     .def = 0.01,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, params.p_hum)},
    {.name = "p_act",
     .type = SCH_NUMBER,
     .desc = "dobashi: probability per step that a cell becomes active (times the ellipsoids' "
             "shape, when there are any).",
     .min = 0,
     .max = 1,
     .def = 0.0005,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, params.p_act)},
    {.name = "wind",
     .type = SCH_NUMBER,
     .desc = "dobashi: the cells move this far along +x per step (fractions accumulate); those "
             "leaving the grid are lost.",
     .unit = "cells/step",
     .min = -64,
     .max = 64,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, params.wind)},
    {.name = "ellipsoids",
     .type = SCH_ARRAY,
     .desc = "Where the initial humidity and the dobashi supply go: none means everywhere.",
     .max = 16,
     .items = &cloud_ellipsoid_item},
    {.name = "metaball_radius",
     .type = SCH_NUMBER,
     .desc = "Effective radius of each cloud cell's Gaussian metaball (sigma = radius / 3); 0 "
             "takes 9 cells at 64 cells along the longest side, scaled with the grid.",
     .unit = "cells",
     .min = 0,
     .max = 64,
     .store = SCH_STORE_F64,
     .offset = offsetof(scene_cloud_t, radius)},
    {.name = "seed",
     .type = SCH_INTEGER,
     .desc = "Seed of the initial cells and of the dobashi draws; changing it seeds fresh cells.",
     .min = 0,
     .max = MAX_SAFE,
     .def = 1,
     .store = SCH_STORE_U64,
     .offset = offsetof(scene_cloud_t, params.seed)},
    {.name = "steps_per_frame",
     .type = SCH_INTEGER,
     .desc = "Automaton steps per simulation step.",
     .min = 1,
     .max = 64,
     .def = 1,
     .store = SCH_STORE_U32,
     .offset = offsetof(scene_cloud_t, steps_per_frame)},
    {.name = "smoothing",
     .type = SCH_NUMBER,
     .desc = "Fraction of the previous density kept at each simulation step, so that growth "
             "fades in instead of popping; 0 shows each new density at once.",
     .min = 0,
     .max = 0.99,
     .def = 0.5,
     .store = SCH_STORE_F32,
     .offset = offsetof(scene_cloud_t, keep)},
    {.name = "init",
     .type = SCH_OBJECT,
     .desc = "How fresh cells are seeded (no cloud cells, random humidity and a few active "
             "cells, drawn from seed); changing it seeds fresh cells.",
     .fields = cloud_init_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "density",
     .type = SCH_NUMBER,
     .desc = "Extinction where the metaball density is 1 (inside a solid cloud).",
     .unit = "1/world unit",
     .min = 0,
     .max = 1e4,
     .def = 8,
     .store = SCH_STORE_F32,
     .offset = offsetof(scene_cloud_t, look.density)},
    {.name = "albedo",
     .type = SCH_VEC3,
     .desc = "Single-scattering albedo, linear RGB.",
     .min = 0,
     .max = 1,
     .def_vec = cloud_albedo,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(scene_cloud_t, look.albedo)},
    {.name = "samples",
     .type = SCH_INTEGER,
     .desc = "Samples per ray inside the cloud's box.",
     .min = 1,
     .max = 4096,
     .def = 64,
     .store = SCH_STORE_INT,
     .offset = offsetof(scene_cloud_t, look.samples)},
    {0},
};

static const sch_field_t scene_fields[] = {
    {.name = "camera",
     .type = SCH_OBJECT,
     .desc = "The pinhole camera the scene is rendered from.",
     .fields = camera_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "background",
     .type = SCH_VEC3,
     .desc = "Linear RGB radiance seen where a ray hits nothing.",
     .min = 0,
     .max = 1000,
     .def_vec = bg_color,
     .store = SCH_STORE_VEC3F,
     .offset = offsetof(render_scene_t, background)},
    {.name = "light",
     .type = SCH_OBJECT,
     .desc = "The directional key light.",
     .fields = light_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "objects",
     .type = SCH_ARRAY,
     .desc = "Opaque objects, drawn and shadowed.",
     .max = 1024,
     .items = &object_item},
    {.name = "waves",
     .type = SCH_ARRAY,
     .desc = "Energy waves, drawn additively and hidden behind the objects.",
     .max = 64,
     .items = &wave_item},
    {.name = "sim",
     .type = SCH_OBJECT,
     .desc = "The simulation clock and its settings.",
     .fields = sim_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "render",
     .type = SCH_OBJECT,
     .desc = "How frames are exposed and tone mapped.",
     .fields = render_fields,
     .store = SCH_STORE_MEMBERS,
     .offset = 0},
    {.name = "fluid",
     .type = SCH_OBJECT,
     .desc = "The SPH particle fluid (SPEC 5.2), drawn as metaballs; its particles are set and "
             "read through fluid.set_particles and fluid.get_particles.",
     .fields = fluid_fields},
    {.name = "volumes",
     .type = SCH_ARRAY,
     .desc = "Volumes of mist or smoke around the objects (layer volumes).",
     .max = 16,
     .items = &volume_item},
    {.name = "cloud",
     .type = SCH_OBJECT,
     .desc = "The cellular-automaton cloud (SPEC 5.4); its cells are read and written through "
             "cloud.get_cells and cloud.set_cells.",
     .fields = cloud_fields},
    {0},
};

const sch_field_t scene_schema = {
    .name = "scene",
    .type = SCH_OBJECT,
    .desc = "A volfx scene: camera, lighting, objects, energy waves, simulation clock and render "
            "settings.",
    .fields = scene_fields,
};

const sch_field_t *scene_schema_at(const char *path) {
  return sch_path_field(&scene_schema, path);
}
