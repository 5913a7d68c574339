/*
 * Glue between the application and the link layer (firmware/link): the
 * callbacks the link calls for host requests, and the main-loop step that
 * runs both and forwards the application's events to the host.
 *
 *   oibar_link_init(&link, &cfg, &port, oibar_app_link_callbacks());
 *   for (;;) oibar_app_link_run_once(&link);
 */
#ifndef OIBAR_APP_LINK_H
#define OIBAR_APP_LINK_H

#include <stdint.h>

#include "oibar/link.h"

const oibar_link_app_t *oibar_app_link_callbacks(void);
/* Send the queued application events, oldest first, until the port refuses
 * one (it stays queued for the next pass); returns how many still wait. */
uint32_t oibar_app_link_forward_events(oibar_link_t *link);
/* One main-loop pass: link poll, application pass, events out. */
void oibar_app_link_run_once(oibar_link_t *link);
/* How many times a send was refused and the event kept for later. */
uint32_t oibar_app_link_events_unsent(void);

#endif
