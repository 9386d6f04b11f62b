/*
 * The render-farm commands of the volfx CLI: `volfx batch` renders a frame range to numbered
 * files and `volfx bake` simulates a shot once into snapshots. Both start a private volfxd of
 * their own, need no running server, and stop it whatever happens.
 */
#ifndef VOLFX_CLI_BATCH_H
#define VOLFX_CLI_BATCH_H

/*
 * Runs `volfx batch ARGS` with 'argv[0]' "batch" and the command's words after it. Returns the
 * exit status: 0 done, 1 a frame or the server failed, 2 a command-line error. After SIGINT or
 * SIGTERM it stops its server and then dies of the same signal.
 */
int cli_batch(int argc, char **argv);

/* Runs `volfx bake ARGS` with 'argv[0]' "bake"; returns an exit status as cli_batch(). */
int cli_bake(int argc, char **argv);

#endif
