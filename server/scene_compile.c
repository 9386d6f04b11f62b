/*
 * Compiling a checked scene document into the snapshot the renderer reads (render_scene.h) and
 * the cloud's settings (scene_cloud_t). Where each field goes and how it is converted is
 * declared once, in its schema entry (scene_schema.c: .store, .offset); this file walks the
 * table with sch_compile for the document's top-level sections and for each item of its
 * arrays, and adds what no field holds: meshes and volume grids from their files, the fluid's
 * particles, the cloud's density and its box.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"
#include "scene_files.h"
#include "scene_internal.h"

/* The index of "u8" in volumes[].format's values (scene_schema.c). */
#define VOLUME_FORMAT_U8 0

/* The grid of file volume 'v' (volumes['i']): a counted reference, or NULL with 'err' set. */
static density_grid_t *volume_grid(const cJSON *v, int i, scene_error_t *err) {
  double d[3];
  sch_vec3d(sch_member(v, "dims"), d);
  uint32_t dims[3] = {(uint32_t)d[0], (uint32_t)d[1], (uint32_t)d[2]};
  return scene_grid_get(
      sch_member(v, "file")->valuestring, i, dims,
      sch_member_enum(scene_schema_at("volumes.0"), v, "format") == VOLUME_FORMAT_U8, err);
}

/* The mesh of mesh object 'o' (objects['i']): a counted reference, or NULL with 'err' set. */
static mesh_t *object_mesh(const cJSON *o, int i, scene_error_t *err) {
  char p[64];
  snprintf(p, sizeof p, "objects.%d.file", i);
  return scene_mesh_get(sch_member(o, "file")->valuestring, p, err);
}

/* Compiles the array 'name' of 'doc' into '*items' (calloc'd, 'size' bytes each; NULL when it
 * is empty), each item by its schema entry; '*n' items. Returns 0, or -1 on OOM. */
static int compile_items(const cJSON *doc, const char *name, void **items, size_t size, int *n) {
  char at[32];
  const cJSON *arr = sch_member(doc, name);
  int count = cJSON_GetArraySize(arr);
  *items = NULL;
  if (count == 0)
    return 0;
  *items = calloc((size_t)count, size);
  if (!*items)
    return -1;
  snprintf(at, sizeof at, "%s.0", name);
  const sch_field_t *item = scene_schema_at(at);
  int i = 0;
  for (const cJSON *v = arr->child; v; v = v->next, i++)
    sch_compile(item, v, (char *)*items + (size_t)i * size);
  *n = count;
  return 0;
}

/* Compiles volumes[] into 'rs', loading grid files. Returns 0, or -1 with 'err' set (the
 * grids taken so far belong to rs and go with it). */
static int compile_volumes(const cJSON *doc, render_scene_t *rs, scene_error_t *err) {
  int n = 0;
  if (compile_items(doc, "volumes", (void **)&rs->volumes, sizeof *rs->volumes, &n) != 0)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  int i = 0;
  for (const cJSON *v = sch_member(doc, "volumes")->child; v; v = v->next, i++) {
    rvolume_t *rv = &rs->volumes[i];
    rs->nvolumes = i + 1;
    if (rv->source == VOLUME_GRID) {
      rv->grid = volume_grid(v, i, err);
      if (!rv->grid)
        return -1;
    }
  }
  return 0;
}

/* Compiles the waves of 'doc' into 'rs' (rs->waves NULL when there are none). Returns 0 or -1
 * on OOM, leaving rs->waves NULL. */
static int compile_waves(const cJSON *doc, render_scene_t *rs) {
  rs->nwaves = 0;
  return compile_items(doc, "waves", (void **)&rs->waves, sizeof *rs->waves, &rs->nwaves);
}

/* Fills rs->fluid from the document and the particles, taking a reference to them when the
 * fluid is drawn; a fluid that is disabled or empty is not drawn. */
static void compile_fluid(const cJSON *doc, particles_t *p, render_scene_t *rs) {
  memset(&rs->fluid, 0, sizeof rs->fluid);
  const cJSON *fluid = sch_member(doc, "fluid");
  if (!cJSON_IsTrue(sch_member(fluid, "enabled")) || !p || p->count == 0)
    return;
  sch_compile(scene_schema_at("fluid"), fluid, &rs->fluid);
  rs->fluid.count = p->count;
  rs->fluid.positions = p->pos;
  rs->fluid.owner = particles_ref(p);
}

int scene_cloud_of(const cJSON *doc, scene_cloud_t *c) {
  const cJSON *cloud = sch_member(doc, "cloud");
  memset(c, 0, sizeof *c);
  sch_compile(scene_schema_at("cloud"), cloud, c);
  double longest = 0;
  for (int i = 0; i < 3; i++)
    longest = fmax(longest, (double)c->n[i]);
  cloud_params_t *p = &c->params;
  for (const cJSON *e = sch_member(cloud, "ellipsoids")->child;
       e && p->nellipsoids < CLOUD_MAX_ELLIPSOIDS; e = e->next) {
    double ce[3], r[3];
    sch_vec3d(sch_member(e, "center"), ce);
    sch_vec3d(sch_member(e, "radii"), r);
    cloud_ellipsoid_t *el = &p->ellipsoids[p->nellipsoids++];
    /* Cell (i, j, k) has its centre at origin + (i + 0.5) voxel. */
    for (int i = 0; i < 3; i++) {
      el->center[i] = (float)((ce[i] - c->origin[i]) / c->voxel - 0.5);
      el->radii[i] = (float)(r[i] / c->voxel);
    }
  }
  if (!(c->radius > 0))
    c->radius = 9.0 * longest / 64;
  return c->enabled ? 0 : -1;
}

/* The cloud of 'doc' showing 'density', that of 'cells' (NULL: step 0), drawn where the wind
 * has carried it: its box moved along +x by the fraction of a cell the wind has moved the
 * cells beyond whole cells (cloud_wind_fraction). */
void scene_compile_cloud(const cJSON *doc, const cloud_cells_t *cells, density_grid_t *density,
                         render_scene_t *rs) {
  memset(&rs->cloud, 0, sizeof rs->cloud);
  if (!density)
    return;
  scene_cloud_t c;
  scene_cloud_of(doc, &c);
  double origin[3] = {c.origin[0], c.origin[1], c.origin[2]};
  origin[0] += cloud_wind_fraction(&c.params, cells ? cells->step : 0) * c.voxel;
  rs->cloud = c.look;
  rs->cloud.source = VOLUME_GRID;
  for (int i = 0; i < 3; i++) {
    rs->cloud.min[i] = (float)origin[i];
    rs->cloud.max[i] = (float)(origin[i] + (double)c.n[i] * c.voxel);
  }
  rs->cloud.grid = density_grid_ref(density);
}

render_scene_t *scene_compile(const cJSON *doc, particles_t *particles, const cloud_cells_t *cells,
                              density_grid_t *cloud, scene_error_t *err) {
  render_scene_t *rs = calloc(1, sizeof *rs);
  if (!rs) {
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  atomic_init(&rs->refs, 1);
  /* The camera, background, light, render settings and clock. */
  sch_compile(&scene_schema, doc, rs);
  int n = 0;
  if (compile_items(doc, "objects", (void **)&rs->objects, sizeof *rs->objects, &n) != 0) {
    render_scene_unref(rs);
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  int i = 0;
  for (const cJSON *o = sch_member(doc, "objects")->child; o; o = o->next, i++) {
    robject_t *ro = &rs->objects[i];
    /* Counted as it goes, so that unref frees exactly the meshes taken so far on failure. */
    rs->nobjects = i + 1;
    if (ro->shape == SHAPE_MESH) {
      ro->mesh = object_mesh(o, i, err);
      if (!ro->mesh) {
        render_scene_unref(rs);
        return NULL;
      }
    }
  }
  if (compile_waves(doc, rs) != 0) {
    render_scene_unref(rs);
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  compile_fluid(doc, particles, rs);
  scene_compile_cloud(doc, cells, cloud, rs);
  if (compile_volumes(doc, rs, err) != 0) {
    render_scene_unref(rs);
    return NULL;
  }
  return rs;
}

int scene_compile_files_ready(const cJSON *doc, scene_error_t *err) {
  const sch_field_t *object = scene_schema_at("objects.0"), *volume = scene_schema_at("volumes.0");
  int i = 0;
  for (const cJSON *o = sch_member(doc, "objects")->child; o; o = o->next, i++) {
    if (sch_member_enum(object, o, "shape") != SHAPE_MESH)
      continue;
    mesh_t *m = object_mesh(o, i, err);
    if (!m)
      return -1;
    mesh_unref(m);
  }
  i = 0;
  for (const cJSON *v = sch_member(doc, "volumes")->child; v; v = v->next, i++) {
    if (sch_member_enum(volume, v, "source") != VOLUME_GRID)
      continue;
    density_grid_t *g = volume_grid(v, i, err);
    if (!g)
      return -1;
    density_grid_unref(g);
  }
  return 0;
}

render_scene_t *scene_compile_advanced(const render_scene_t *old, const cJSON *doc,
                                       particles_t *particles, uint64_t frame, double time) {
  render_scene_t *rs = malloc(sizeof *rs);
  if (!rs)
    return NULL;
  memcpy(rs, old, sizeof *rs);
  atomic_init(&rs->refs, 1);
  rs->objects = NULL;
  rs->volumes = NULL;
  if (compile_waves(doc, rs) != 0) {
    free(rs);
    return NULL;
  }
  if (old->nobjects > 0) {
    rs->objects = malloc((size_t)old->nobjects * sizeof *rs->objects);
    if (!rs->objects) {
      free(rs->waves);
      free(rs);
      return NULL;
    }
    memcpy(rs->objects, old->objects, (size_t)old->nobjects * sizeof *rs->objects);
    for (int i = 0; i < rs->nobjects; i++)
      if (rs->objects[i].mesh)
        mesh_ref(rs->objects[i].mesh);
  }
  if (old->nvolumes > 0) {
    rs->volumes = malloc((size_t)old->nvolumes * sizeof *rs->volumes);
    if (!rs->volumes) {
      for (int i = 0; i < rs->nobjects; i++)
        if (rs->objects[i].mesh)
          mesh_unref(rs->objects[i].mesh);
      free(rs->objects);
      free(rs->waves);
      free(rs);
      return NULL;
    }
    memcpy(rs->volumes, old->volumes, (size_t)old->nvolumes * sizeof *rs->volumes);
    for (int i = 0; i < rs->nvolumes; i++)
      density_grid_ref(rs->volumes[i].grid);
  }
  density_grid_ref(rs->cloud.grid);
  compile_fluid(doc, particles, rs);
  rs->frame = frame;
  rs->time = time;
  return rs;
}
