// A VDA 5050 2.0 master control for the tests: vda-5050-lib's MasterController (third-party code) on an MQTT broker.
// Usage: node master.js BROKER_URL INTERFACE MANUFACTURER SERIAL[,SERIAL...] (several serial numbers: one master for
// a fleet, every AGV of that manufacturer targeted).
// Commands arrive as JSON lines on stdin, events leave as JSON lines on stdout:
//   {"cmd": "assign", "order": {...headerless order...}, "serialNumber": "r2"}   -> "assigned" / "assignFailed", then
//                                                                                  order events
//   {"cmd": "instant", "actions": [...], "serialNumber": "r2"}                    -> "instantSent", then action events
//   {"cmd": "stop"}
// "serialNumber" defaults to the first one given. Every event names its AGV's serialNumber.
// Events: connection, state (summary of every state), orderProcessed, nodeTraversed, edgeTraversed, actionState,
// actionError. Inbound messages that fail the library's own 2.0 validation are dropped by it with a console.error
// line on stderr, which the tests read.
"use strict";
const readline = require("readline");
const { MasterController } = require("vda-5050-lib");

const [brokerUrl, interfaceName, manufacturer, serialList] = process.argv.slice(2);
const serialNumbers = serialList.split(",");
const agvOf = (serialNumber) => ({ manufacturer, serialNumber: serialNumber || serialNumbers[0] });
const emit = (event) => process.stdout.write(JSON.stringify({ t: Date.now(), ...event }) + "\n");

const mc = new MasterController(
    { interfaceName, transport: { brokerUrl, heartbeat: 2, reconnectPeriod: 200 }, vdaVersion: "2.0.0" },
    { targetAgvs: serialNumbers.length > 1 ? { manufacturer } : agvOf(serialNumbers[0]) });

function orderKey(order, serialNumber) {
    return { serialNumber, orderId: order.orderId, orderUpdateId: order.orderUpdateId };
}

async function main() {
    await mc.start();
    mc.trackAgvs((subject, state, timestamp) => emit({
        event: "connection", serialNumber: subject.serialNumber, state, timestamp }));
    for (const serialNumber of serialNumbers) {
        await mc.subscribe("state", agvOf(serialNumber), (state) => emit({
            event: "state", serialNumber: state.serialNumber, headerId: state.headerId, orderId: state.orderId,
            orderUpdateId: state.orderUpdateId, lastNodeId: state.lastNodeId,
            lastNodeSequenceId: state.lastNodeSequenceId, driving: state.driving, paused: state.paused,
            nodeStates: state.nodeStates, edgeStates: state.edgeStates, actionStates: state.actionStates,
            errors: state.errors, safetyState: state.safetyState, agvPosition: state.agvPosition,
            velocity: state.velocity, operatingMode: state.operatingMode, batteryState: state.batteryState,
        }));
    }
    emit({ event: "started" });
    const lines = readline.createInterface({ input: process.stdin });
    for await (const line of lines) {
        if (!line.trim()) continue;
        const command = JSON.parse(line);
        if (command.cmd === "stop") break;
        const agvId = agvOf(command.serialNumber);
        const serialNumber = agvId.serialNumber;
        if (command.cmd === "assign") {
            const order = command.order;
            try {
                const sent = await mc.assignOrder(agvId, order, {
                    onOrderProcessed: (error, byCancelation, active, ctx) => emit({
                        event: "orderProcessed", ...orderKey(order, serialNumber), error: error || null,
                        byCancelation, active, position: ctx.state.agvPosition || null }),
                    onNodeTraversed: (node, nextEdge, nextNode, ctx) => emit({
                        event: "nodeTraversed", ...orderKey(order, serialNumber), nodeId: node.nodeId,
                        sequenceId: node.sequenceId, position: ctx.state.agvPosition || null }),
                    onEdgeTraversed: (edge) => emit({
                        event: "edgeTraversed", ...orderKey(order, serialNumber), edgeId: edge.edgeId }),
                    onActionStateChanged: (actionState, error) => emit({
                        event: "orderActionState", ...orderKey(order, serialNumber), actionState,
                        error: error || null }),
                });
                emit({
                    event: sent ? "assigned" : "discarded", ...orderKey(order, serialNumber),
                    headerId: sent ? sent.headerId : null });
            } catch (err) {
                emit({ event: "assignFailed", ...orderKey(order, serialNumber), message: String(err && err.message) });
            }
        } else if (command.cmd === "instant") {
            try {
                const sent = await mc.initiateInstantActions(agvId, { instantActions: command.actions }, {
                    onActionStateChanged: (actionState, error, action) => emit({
                        event: "actionState", serialNumber, actionId: action.actionId, actionType: action.actionType,
                        actionStatus: actionState.actionStatus, error: error || null }),
                    onActionError: (error, action) => emit({
                        event: "actionError", serialNumber, actionId: action.actionId, actionType: action.actionType,
                        error }),
                });
                emit({ event: "instantSent", serialNumber, headerId: sent.headerId });
            } catch (err) {
                emit({ event: "instantFailed", serialNumber, message: String(err && err.message) });
            }
        }
    }
    await mc.stop();
    process.exit(0);
}

main().catch((err) => { emit({ event: "fatal", message: String(err && err.stack) }); process.exit(1); });
