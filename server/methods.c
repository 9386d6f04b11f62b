/* The method table: every method volfxd answers, in the order rpc.discover lists them. */
#include "dispatch.h"

extern const method_t method_server_info, method_rpc_discover, method_auth, method_stats,
    method_server_shutdown, method_scene_list, method_scene_create, method_scene_delete,
    method_scene_get, method_scene_set, method_scene_save, method_scene_load, method_sim_step,
    method_sim_play, method_sim_pause, method_render, method_frames_subscribe,
    method_frames_unsubscribe, method_fluid_set_particles, method_fluid_get_particles,
    method_cloud_get_cells, method_cloud_set_cells, method_render_sequence, method_job_list,
    method_job_cancel;

const method_t *const method_table[] = {
    &method_server_info,
    &method_rpc_discover,
    &method_auth,
    &method_scene_list,
    &method_scene_create,
    &method_scene_delete,
    &method_scene_get,
    &method_scene_set,
    &method_scene_save,
    &method_scene_load,
    &method_sim_step,
    &method_sim_play,
    &method_sim_pause,
    &method_render,
    &method_frames_subscribe,
    &method_frames_unsubscribe,
    &method_render_sequence,
    &method_job_list,
    &method_job_cancel,
    &method_fluid_set_particles,
    &method_fluid_get_particles,
    &method_cloud_get_cells,
    &method_cloud_set_cells,
    &method_stats,
    &method_server_shutdown,
    NULL,
};
